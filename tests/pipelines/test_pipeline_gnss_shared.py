"""gnss_tight's per-epoch sharing (issue 16's speed target): one prediction at the centre serves the fault
test over time, the residual tests and RAIM, instead of each building its own model. Held to the
computations each did alone (the functions without the shared argument) on the real recording, UPF and UKF,
with a ramp on one satellite so that RAIM's exclusion retests a subset of rows."""

from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest
from edgepos.core import state as state_format
from edgepos.core.integrity import _radial_factors, radial_factor_table
from edgepos.core.motion import riss as layout
from edgepos.core.observations import PseudorangeObservation
from edgepos.core.particles.base import weighted_moments
from edgepos.gnss.measurements import PseudorangeSet
from edgepos.gnss.raim import Separations
from edgepos.pipelines import gnss_tight
from edgepos.pipelines.base import Fix, MeasurementUse, StaticEnvironment
from edgepos.pipelines.gnss_integrity import EXCLUDED, WARM_HYPOTHESES, warm_up_gnss_tables
from edgepos.pipelines.gnss_satellites import EpochSatellites, replaced
from edgepos.pipelines.gnss_screening import group_rows, left_out, median
from edgepos.pipelines.gnss_session import cloud_moments, decode_session
from gnssrecording import recording_epochs

EPOCHS = 45


@pytest.fixture(scope="module")
def recording() -> tuple[list[list[PseudorangeObservation]], StaticEnvironment]:
    """The first EPOCHS epochs with carrier phase, one GPS satellite's pseudorange ramped from epoch 15."""
    epochs, environment, _ = recording_epochs(EPOCHS)
    victim = min((o.system, o.prn) for o in epochs[0] if o.system == "G")
    ramped = [
        [
            dataclasses.replace(o, pseudorange=o.pseudorange + 4.0 * max(k - 15, 0))
            if (o.system, o.prn) == victim
            else o
            for o in epoch
        ]
        for k, epoch in enumerate(epochs)
    ]
    return ramped, environment


def _run(epochs, environment, options) -> list[Fix]:
    pipeline = gnss_tight.GnssTightPipeline()
    state = pipeline.create(pipeline.resolve_options({"seed": 3, **options}), None)
    fixes = []
    for epoch in epochs:
        (fix,), state = pipeline.process(state, epoch, environment)
        fixes.append(fix)
    return fixes


def _held_to_alone(function, shared_position: int, seen: list[int]):  # type: ignore[no-untyped-def]
    """``function`` called with the shared prediction (positional ``shared_position``) and again without it
    (its own model), on copies of whatever it writes to: both must return and write the same."""

    def call(*args):  # type: ignore[no-untyped-def]
        assert len(args) == shared_position + 1 and args[shared_position] is not None
        own_args = copy.deepcopy(args[:shared_position])
        result = function(*args)
        own = function(*own_args)
        for a, b in zip(
            result if isinstance(result, tuple) else (result,), own if isinstance(own, tuple) else (own,)
        ):
            if isinstance(a, Separations):
                assert a.available == b.available and a.threshold == b.threshold
                assert len(a.hypotheses) == len(b.hypotheses)
                for x, y in zip(a.hypotheses, b.hypotheses):
                    assert x[0] == y[0] and x[4] == y[4]
                    assert np.allclose(x[1], y[1], rtol=1e-9, atol=1e-9)
                    assert np.allclose(x[2], y[2], rtol=1e-9, atol=1e-12)
                    assert x[3] == pytest.approx(y[3], rel=1e-9, abs=1e-9)
            else:
                assert np.allclose(a, b, rtol=1e-12, atol=1e-9)
        for written, own_written in zip(args[:shared_position], own_args):
            if isinstance(written, dict):  # the uses and Doppler reports
                assert written == own_written
        seen.append(1)
        return result

    return call


ONLY_RAIM = {"fault_probability": 0.0, "fde_probability": 0.0, "gate_probability": 0.0}
"""The other screens off, so that RAIM excludes the ramp and retests the rows left."""


@pytest.mark.parametrize("numba", ["1", "0"])
@pytest.mark.parametrize(
    ("options", "reason"),
    [({"filter": "upf"}, "excluded over time"), ({"filter": "ukf", **ONLY_RAIM}, EXCLUDED)],
)
def test_shared_predictions_give_what_each_test_computes_alone(
    recording, monkeypatch, options, reason, numba
) -> None:
    """With the compiled predictions (core/measurements/gnss_kernel.py ``pseudoranges_at``,
    ``range_rates_at``) and with the numpy models (EDGEPOS_NUMBA=0)."""
    monkeypatch.setenv("EDGEPOS_NUMBA", numba)
    seen: dict[str, list[int]] = {}
    for name, position in (
        ("range_innovations", 7),
        ("rate_innovations", 6),
        ("residual_test", 11),
        ("range_rate_test", 10),
        ("detect_and_exclude", 13),
    ):
        seen[name] = []
        monkeypatch.setattr(gnss_tight, name, _held_to_alone(getattr(gnss_tight, name), position, seen[name]))
    fixes = _run(*recording, options)
    assert any(use.reason and use.reason.startswith(reason) for f in fixes for use in f.measurements)
    assert len(seen["detect_and_exclude"]) > EPOCHS // 2 and len(seen["range_rate_test"]) > EPOCHS // 2
    if options.get("fault_probability", 1.0) != 0.0:
        assert len(seen["range_innovations"]) > EPOCHS // 2 and len(seen["rate_innovations"]) > EPOCHS // 2


def test_the_screens_median_is_numpys() -> None:
    rng = np.random.default_rng(5)
    for count in range(1, 12):
        for _ in range(20):
            values = rng.normal(0.0, 30.0, count) + rng.integers(-3, 3, count)  # with ties now and then
            assert median(values) == float(np.median(values))


def test_rows_left_out_are_setdiff1d() -> None:
    rng = np.random.default_rng(6)
    for _ in range(50):
        rows = np.flatnonzero(rng.random(25) < 0.7)
        kept = rows[rng.random(rows.size) < 0.8]
        assert left_out(rows, kept) == np.setdiff1d(rows, kept).tolist()


def test_the_warmed_up_raim_tables_serve_the_recording(recording) -> None:
    """After the start-up warm-up, epochs of the recording (about 20 satellites, three constellations)
    compute no radial table of their own (each would cost about 50 ms of quadrature in the filter thread)."""
    _radial_factors.cache_clear()
    radial_factor_table.cache_clear()
    warm_up_gnss_tables()
    warmed = _radial_factors.cache_info().misses
    assert warmed == 1 + len(
        WARM_HYPOTHESES
    )  # the fault-free share and one per count (default P_sat = P_const)
    fixes = _run(*recording, {"filter": "upf"})
    assert sum(f.protection_level is not None for f in fixes) > EPOCHS // 2
    assert _radial_factors.cache_info().misses == warmed


@pytest.mark.parametrize("cls", [MeasurementUse, Fix])
def test_reports_are_copied_as_dataclasses_replace_would(cls: type) -> None:
    """gnss_tight's ``_with`` copies a fix or a measurement report without running ``__init__``; that holds
    only while the class has no ``__post_init__`` and no slots, and it must give replace's result."""
    assert not hasattr(cls, "__post_init__") and not hasattr(cls, "__slots__")
    original = cls(4.0, "tracking") if cls is Fix else cls(4, "pseudorange", True, noise_std=1.5)
    changes = {"nis": 2.5, "nis_dof": 3} if cls is Fix else {"doppler_used": False, "doppler_reason": "why"}
    before = dict(original.__dict__)
    copied = gnss_tight._with(original, **changes)
    assert copied == dataclasses.replace(original, **changes) and copied is not original
    assert type(copied) is cls and original.__dict__ == before  # the original unchanged
    with pytest.raises(dataclasses.FrozenInstanceError):
        copied.index = 1  # type: ignore[misc]  # still frozen


def test_satellites_are_copied_as_dataclasses_replace_would() -> None:
    """gnss_satellites' ``replaced`` copies an epoch's pseudorange set or satellites without ``__init__``
    (both classes without ``__post_init__`` and slots), the set keeping its formatted satellite names; the
    same fields as replace's, and the names may not be changed through it."""
    for cls in (PseudorangeSet, EpochSatellites):
        assert not hasattr(cls, "__post_init__") and not hasattr(cls, "__slots__")
    prs = PseudorangeSet(
        1.0e5,
        ("G", "E"),
        np.array([3, 11]),
        np.array([2.1e7, 2.3e7]),
        np.array([40.0, 35.0]),
        np.ones((2, 3)),
        np.zeros(2),
        np.full(2, 1575.42e6),
    )
    assert prs.sats == ("G03", "E11")
    copied = replaced(prs, pseudorange_m=np.array([1.0, 2.0]))
    reference = dataclasses.replace(prs, pseudorange_m=np.array([1.0, 2.0]))
    for field in dataclasses.fields(PseudorangeSet):
        np.testing.assert_array_equal(getattr(copied, field.name), getattr(reference, field.name))
    assert copied.sats == reference.sats and prs.pseudorange_m[0] == 2.1e7
    with pytest.raises(dataclasses.FrozenInstanceError):
        copied.gpst = 0.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="names"):
        replaced(prs, prns=np.array([4, 12]))
    satellites = EpochSatellites(prs, [0, 1], {})
    moved = replaced(satellites, prs=copied, corrected=np.array([True, False]))
    assert moved.prs is copied and moved.indices == [0, 1] and satellites.corrected is None
    assert type(moved) is EpochSatellites and moved.corrected is not None


def test_the_upf_state_carries_its_clouds_moments(recording) -> None:  # type: ignore[no-untyped-def]
    """The UPF's step knows its new cloud's weighted moments; the state stores them beside the particles
    (not after a resampling, which makes a new cloud), and the next epoch reads them instead of computing
    them: they are the weighted moments of the stored particles (to the compiled loop's rounding). A state
    without them (written before) still decodes and computes them; corrupt ones are refused."""
    epochs, environment = recording
    pipeline = gnss_tight.GnssTightPipeline()
    state = pipeline.create(pipeline.resolve_options({"seed": 3, "filter": "upf", "particles": 200}), None)
    carried = 0
    for epoch in epochs[:25]:
        _, state = pipeline.process(state, epoch, environment)
        meta, arrays = state_format.unpack(state)
        if "moments_mean" not in arrays:
            continue
        carried += 1
        mean, cov = weighted_moments(arrays["particles"], np.exp(arrays["log_weights"]), layout.ANGLES)
        np.testing.assert_allclose(arrays["moments_mean"], mean, rtol=0.0, atol=1e-9)
        np.testing.assert_allclose(arrays["moments_cov"], cov, rtol=1e-9, atol=1e-12)
        session = decode_session(state)
        assert session.cloud.known_moments(layout.ANGLES) is not None
        np.testing.assert_array_equal(cloud_moments(session)[0], arrays["moments_mean"])
    assert 0 < carried < 25  # carried, and not after the epochs that resampled
    meta, arrays = state_format.unpack(state)
    arrays.pop("moments_mean", None), arrays.pop("moments_cov", None)
    older = decode_session(state_format.pack(meta, arrays))
    assert older.cloud.known_moments(layout.ANGLES) is None
    pipeline.process(state_format.pack(meta, arrays), epochs[25], environment)
    arrays["moments_mean"], arrays["moments_cov"] = np.zeros(3), np.zeros((3, 3))
    with pytest.raises(state_format.StateFormatError, match="moments"):
        decode_session(state_format.pack(meta, arrays))


def test_the_state_keeps_its_options_as_text(recording) -> None:  # type: ignore[no-untyped-def]
    """The options travel as their JSON text (``options_json``), parsed once per distinct text: each epoch
    writes back the text it read, the same fixes come from a state holding the options themselves (written
    before the text), options changed after decoding are written anew, and a corrupt text is refused."""
    epochs, environment = recording
    pipeline = gnss_tight.GnssTightPipeline()
    options = pipeline.resolve_options({"seed": 3, "filter": "ukf"})
    state = pipeline.create(options, None)
    meta, arrays = state_format.unpack(state)
    assert "options" not in meta and json.loads(meta["options_json"]) == options
    old_meta = {key: value for key, value in meta.items() if key != "options_json"}
    old = state_format.pack({**old_meta, "options": options}, arrays)
    for epoch in epochs[:5]:
        (fix,), state = pipeline.process(state, epoch, environment)
        (old_fix,), old = pipeline.process(old, epoch, environment)
        assert fix == old_fix and state == old
        assert state_format.unpack(state)[0]["options_json"] == meta["options_json"]
    session = decode_session(state)
    assert session.options == options and session.options is not decode_session(state).options
    session.options["elevation_mask"] = 0.2
    assert json.loads(state_format.unpack(session.to_bytes())[0]["options_json"])["elevation_mask"] == 0.2
    assert decode_session(state).options == options  # the parse of the original text is not touched
    meta, arrays = state_format.unpack(state)
    for corrupt in ("{not json", "[1, 2]", 5):
        with pytest.raises(state_format.StateFormatError, match="options"):
            decode_session(state_format.pack({**meta, "options_json": corrupt}, arrays))


def test_the_scores_medians_are_per_group() -> None:
    """``normalised_scores`` removes each group's median (three rows or more) from its rows only: the
    boolean-mask form it replaced, bit for bit, on groups interleaved as an epoch's constellations are."""
    from edgepos.pipelines.gnss_faults import normalised_scores

    rng = np.random.default_rng(11)
    for count in (1, 2, 5, 9, 20, 31):
        residual = rng.normal(0.0, 5.0, count)
        variance = rng.uniform(1.0, 9.0, count)
        groups = [("G", "C", "E", "R")[k] for k in rng.integers(0, 4, count)]
        centred = residual.copy()
        labels = np.array(groups)
        for group in set(groups):
            members = labels == group
            if members.sum() >= 3:
                centred[members] -= np.median(centred[members])
        np.testing.assert_array_equal(normalised_scores(residual, variance, groups), centred**2 / variance)
        members = group_rows(groups)
        assert sorted(members) == sorted(set(groups))
        for group, rows in members.items():
            assert rows == np.flatnonzero(labels == group).tolist()


def test_the_jacobian_has_one_clock_column_per_constellation() -> None:
    """``jacobian``: the ranges' derivatives by north, east and up, then a 1 in the column of each row's
    constellation (sorted by name), as a row-by-row loop over ``groups.index`` gives."""
    from edgepos.pipelines.gnss_integrity import jacobian

    rng = np.random.default_rng(4)
    for systems in (["G"] * 6, ["G", "E", "C", "G", "C", "E", "E"], ["E", "C", "C", "C", "C"]):
        ranges = rng.normal(size=(4, len(systems)))
        groups = sorted(set(systems))
        expected = np.zeros((len(systems), 3 + len(groups)))
        expected[:, :3] = ranges[1:].T
        for row, system in enumerate(systems):
            expected[row, 3 + groups.index(system)] = 1.0
        np.testing.assert_array_equal(jacobian(ranges, systems), expected)
