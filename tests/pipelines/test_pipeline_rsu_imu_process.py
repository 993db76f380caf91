"""rsu_imu processing: batch validation, epochs, statuses, RSU selection, gating, overrides,
state bytes and determinism."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from edgepos.core import state as state_format
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.pipelines import lag
from edgepos.pipelines.base import (
    Fix,
    InitialState,
    MeasurementUse,
    PipelineInputError,
    Rsu,
    StaticEnvironment,
)
from edgepos.pipelines.epochs import group_by_time
from edgepos.pipelines.registry import get_pipeline
from edgepos.pipelines.rsu_imu import _decode
from edgepos.pipelines.rsu_imu_batch import batch_epochs, epoch_measurements, epoch_parts, read_batch

RSUS = (
    Rsu("S000", 0.0, -4.0),
    Rsu("N050", 50.0, 15.0),
    Rsu("S100", 100.0, -4.0),
    Rsu("N150", 150.0, 15.0),
    Rsu("S200", 200.0, -4.0),
    Rsu("N250", 250.0, 15.0),
    Rsu("FAR", 2000.0, 0.0),
)
ENV = StaticEnvironment({rsu.id: rsu for rsu in RSUS})
RANGE_STD, BEARING_STD, GYRO_STD = 0.6, math.radians(0.5), math.radians(0.3)
SPEED, DT = 10.0, 0.1


@pytest.fixture(scope="module")
def pipeline():
    return get_pipeline("rsu_imu")


def true_position(t: float) -> tuple[float, float]:
    return 20.0 + SPEED * t, 0.0


def epoch(
    t: float, rng: np.random.Generator, env: StaticEnvironment = ENV, ids=None, gyro: bool = True
) -> list[Observation]:
    """Noisy observations at time t of the vehicle driving east along y = 0."""
    x, y = true_position(t)
    out: list[Observation] = []
    for rsu in env.rsus.values():
        if ids is not None and rsu.id not in ids:
            continue
        dx, dy = x - rsu.x, y - rsu.y
        out.append(
            RsuObservation(
                t=t,
                rsu_id=rsu.id,
                range=math.hypot(dx, dy) + RANGE_STD * rng.standard_normal(),
                bearing=math.remainder(math.atan2(dy, dx) + BEARING_STD * rng.standard_normal(), 2 * math.pi),
            )
        )
    if gyro:
        out.append(GyroObservation(t=t, yaw_rate=GYRO_STD * rng.standard_normal()))
    return out


def started(pipeline, options=None) -> bytes:
    x, y = true_position(0.0)
    return pipeline.create(pipeline.resolve_options(options), InitialState(x, y, SPEED, 0.0, 0.5, 0.5))


def run(
    pipeline, state: bytes, epochs: int, seed: int, start: int = 1, env=ENV, **kw
) -> tuple[list[Fix], bytes]:
    rng = np.random.default_rng(seed)
    fixes: list[Fix] = []
    for k in range(start, start + epochs):
        new, state = pipeline.process(state, epoch(k * DT, rng, env, **kw), env)
        fixes.extend(new)
    return fixes, state


def position_error(fix: Fix) -> float:
    x, y = true_position(fix.t)
    return math.hypot(fix.x - x, fix.y - y)


# -- validation -------------------------------------------------------------------------------------
MAX_DELAY = lag.DEFAULTS["max_delay_s"]  # the lag window: older measurements are too late (reported unused)


def test_bad_batch_is_refused_whole_listing_every_bad_index(pipeline) -> None:
    _, state = run(pipeline, started(pipeline), 5, seed=1)
    last_t = 5 * DT
    rng = np.random.default_rng(2)
    good = epoch(last_t + DT, rng)
    batch = [
        good[0],
        RsuObservation(t=last_t + DT, rsu_id="NOPE", range=10.0, bearing=0.1),  # 1: unknown RSU
        good[1],
        RsuObservation(t=last_t + DT, rsu_id="S000", range=-0.5, bearing=0.1),  # 3: negative range
        GyroObservation(t=last_t - DT, yaw_rate=0.0),  # 4: late, inside the lag window: fine
        # 5: too late for the lag window (not filtered), and two problems of its own
        RsuObservation(t=last_t - 2 * MAX_DELAY, rsu_id="ALSO_NOPE", range=-1.0, bearing=0.0),
        good[-1],
        RsuObservation(t=math.inf, rsu_id="S000", range=10.0, bearing=0.1),  # 7: no time at all
    ]
    with pytest.raises(PipelineInputError) as caught:
        pipeline.process(state, batch, ENV)
    problems = {(p.index, p.field) for p in caught.value.problems}
    assert problems == {(1, "rsu_id"), (3, "range"), (5, "rsu_id"), (5, "range"), (7, "t")}
    assert all(p.reason for p in caught.value.problems)
    # nothing was applied: the same state accepts the good part and gives what it would have anyway
    fixes_a, state_a = pipeline.process(state, [o for i, o in enumerate(batch) if i in (0, 2, 4, 6)], ENV)
    fixes_b, state_b = pipeline.process(state, [good[0], good[1], batch[4], good[-1]], ENV)
    assert state_a == state_b and fixes_a == fixes_b
    assert [(f.t, f.revised) for f in fixes_a] == [(last_t - DT, True), (last_t, True), (last_t + DT, False)]


def test_a_malformed_late_measurement_is_listed_with_every_other_problem_of_the_batch(pipeline) -> None:
    """A late measurement (inside the lag window) is validated as it is filtered again from a checkpoint,
    the batch's new epochs after it: the problems of both parts are listed together."""
    _, state = run(pipeline, started(pipeline), 5, seed=1)
    last_t = 5 * DT
    batch = [
        RsuObservation(t=last_t - DT / 2, rsu_id="NOPE", range=10.0, bearing=0.1),  # late, unknown RSU
        RsuObservation(t=last_t + DT, rsu_id="ALSO_NOPE", range=10.0, bearing=0.1),  # new, unknown RSU
    ]
    for alone in ([batch[0]], [batch[1]]):
        with pytest.raises(PipelineInputError) as caught:
            pipeline.process(state, alone, ENV)
        assert [(p.index, p.field) for p in caught.value.problems] == [(0, "rsu_id")]
    with pytest.raises(PipelineInputError) as caught:
        pipeline.process(state, batch, ENV)
    assert sorted((p.index, p.field) for p in caught.value.problems) == [(0, "rsu_id"), (1, "rsu_id")]


@pytest.mark.parametrize(
    ("observation", "field"),
    [
        (RsuObservation(t=float("nan"), rsu_id="S000", range=10.0, bearing=0.0), "t"),
        (RsuObservation(t=1.0, rsu_id="S000", range=float("inf"), bearing=0.0), "range"),
        (RsuObservation(t=1.0, rsu_id="S000", range=10.0, bearing=4.0), "bearing"),
        (RsuObservation(t=1.0, rsu_id="S000", range=10.0, bearing=float("nan")), "bearing"),
        (GyroObservation(t=1.0, yaw_rate=float("nan")), "yaw_rate"),
    ],
)
def test_non_finite_or_out_of_range_values_are_refused(
    pipeline, observation: Observation, field: str
) -> None:
    with pytest.raises(PipelineInputError) as caught:
        pipeline.process(started(pipeline), [observation], ENV)
    assert [(p.index, p.field) for p in caught.value.problems] == [(0, field)]


def test_time_equal_to_the_last_epoch_is_accepted_and_older_than_the_lag_window_is_not_used(pipeline) -> None:
    """Equal to the last epoch: joins it (its fix comes back revised). Older, inside the lag window: a new
    epoch at its own time, the later fix revised. Older than the window: not used, said so in the newest
    fix (the session's newest epoch again), the session unchanged."""
    _, state = run(pipeline, started(pipeline), 3, seed=3)
    last_t = 3 * DT
    fixes, _ = pipeline.process(state, [GyroObservation(t=last_t, yaw_rate=0.0)], ENV)
    assert [(f.t, f.revised) for f in fixes] == [(last_t, True)]
    assert [(u.index, u.used) for u in fixes[0].measurements] == [(0, True)]
    just_before = math.nextafter(last_t, 0.0)
    fixes, _ = pipeline.process(state, [GyroObservation(t=just_before, yaw_rate=0.0)], ENV)
    assert [(f.t, f.revised) for f in fixes] == [(just_before, False), (last_t, True)]
    assert [(u.index, u.used) for u in fixes[0].measurements] == [(0, True)] and fixes[1].measurements == []
    too_late = math.nextafter(last_t - MAX_DELAY, -math.inf)
    fixes, same = pipeline.process(state, [GyroObservation(t=too_late, yaw_rate=0.0)], ENV)
    assert [(f.t, f.revised) for f in fixes] == [(last_t, True)]
    [use] = fixes[0].measurements
    assert (use.index, use.used) == (0, False) and use.reason.startswith(f"too late: t={too_late!r}")
    assert same == state


# -- epochs -----------------------------------------------------------------------------------------
def test_observations_sharing_a_timestamp_form_one_epoch_and_batches_are_sorted(pipeline) -> None:
    state = started(pipeline)
    rng = np.random.default_rng(4)
    epochs = [epoch(k * DT, rng) for k in range(1, 6)]
    in_order = [o for e in epochs for o in e]
    fixes_sorted, _state_sorted = pipeline.process(state, in_order, ENV)
    assert [f.t for f in fixes_sorted] == [k * DT for k in range(1, 6)]
    shuffled_order = np.random.default_rng(5).permutation(len(in_order))
    shuffled = [in_order[i] for i in shuffled_order]
    fixes_shuffled, _state_shuffled = pipeline.process(state, shuffled, ENV)
    assert [f.t for f in fixes_shuffled] == [f.t for f in fixes_sorted]
    # measurement reports refer to the indices of the list passed in
    for fix in fixes_shuffled:
        for use in fix.measurements:
            assert shuffled[use.index].t == fix.t
            assert shuffled[use.index].kind == use.kind
        assert len(fix.measurements) == sum(o.t == fix.t for o in shuffled)
    # within an epoch only the order of RSUs changes, so the estimates agree closely
    for a, b in zip(fixes_sorted, fixes_shuffled):
        assert a.x == pytest.approx(b.x, abs=1e-9) and a.y == pytest.approx(b.y, abs=1e-9)


def test_statuses_from_uninitialised_to_tracking(pipeline) -> None:
    state = pipeline.create(pipeline.resolve_options(None), None)
    assert pipeline.summarise(state).initialised is False
    rng = np.random.default_rng(6)
    fixes, state = pipeline.process(state, [GyroObservation(t=0.1, yaw_rate=0.0)], ENV)
    assert [f.status for f in fixes] == ["uninitialised"]
    assert fixes[0].x is None and fixes[0].position_cov is None
    assert fixes[0].measurements[0].used is False and fixes[0].measurements[0].reason
    # an RSU beyond its radius cannot initialise either
    far = RsuObservation(t=0.2, rsu_id="FAR", range=1980.0, bearing=math.pi)
    fixes, state = pipeline.process(state, [far], ENV)
    assert fixes[0].status == "uninitialised"
    fixes, state = pipeline.process(state, epoch(0.3, rng), ENV)
    assert fixes[0].status == "initialised"
    assert pipeline.summarise(state).initialised is True
    assert position_error(fixes[0]) < 3.0
    fixes, state = pipeline.process(state, epoch(0.4, rng) + epoch(0.5, rng), ENV)
    assert [f.status for f in fixes] == ["tracking", "tracking"]
    # an epoch with nothing usable is a prediction
    fixes, state = pipeline.process(state, [dataclasses.replace(far, t=0.6)], ENV)
    assert fixes[0].status == "predicted"
    summary = pipeline.summarise(state)
    assert summary.epochs == 6 and summary.t == pytest.approx(0.6)
    assert abs(sum(summary.model_probabilities.values()) - 1.0) < 1e-12


def test_self_initialised_session_converges(pipeline) -> None:
    state = pipeline.create(pipeline.resolve_options(None), None)
    fixes, _ = run(pipeline, state, 60, seed=7)
    assert fixes[0].status == "initialised"
    assert all(f.status == "tracking" for f in fixes[1:])
    assert max(position_error(f) for f in fixes[30:]) < 1.0
    assert fixes[-1].speed == pytest.approx(SPEED, abs=1.0)


# -- RSU selection, gate, handling, overrides ---------------------------------------------------------
def test_rsus_beyond_the_radius_and_beyond_max_rsus_are_reported_unused(pipeline) -> None:
    state = started(pipeline, {"max_rsus": 3})
    fixes, _ = pipeline.process(state, epoch(DT, np.random.default_rng(8)), ENV)
    uses = {use.index: use for use in fixes[0].measurements}
    batch = epoch(DT, np.random.default_rng(8))
    by_id = {o.rsu_id: i for i, o in enumerate(batch) if isinstance(o, RsuObservation)}
    beyond = [i for i in by_id.values() if batch[i].range > 160.0]
    assert {batch[i].rsu_id for i in beyond} == {"FAR", "S200", "N250"}
    for i in beyond:
        assert not uses[i].used and "160 m communication radius" in uses[i].reason
    in_radius = sorted((batch[i].range, i) for i in by_id.values() if batch[i].range <= 160.0)
    assert len(in_radius) == 4
    for _, i in in_radius[:3]:
        assert uses[i].used, uses[i]
    for _, i in in_radius[3:]:
        assert not uses[i].used and "nearest 3" in uses[i].reason
    gyro_index = len(batch) - 1
    assert uses[gyro_index].used and uses[gyro_index].kind == "gyro"
    assert fixes[0].nis_dof == 2 * 3 + 1


def test_a_batchs_epochs_take_the_arrays_epoch_by_epoch_selection_gives(pipeline) -> None:
    """``batch_epochs`` (every epoch's rows taken at once, each epoch's arrays slices of them) gives each
    epoch the RSUs, gyros, records and arrays of ``epoch_parts`` and ``epoch_measurements``, in the
    layout the kernels take (contiguous float64)."""
    options = pipeline.inner.inner.resolve_options({"max_rsus": 3, "rsu_handling": "average"})
    rng = np.random.default_rng(12)
    batch_observations = [o for k in range(1, 6) for o in epoch(k * DT, rng, gyro=k != 3)]
    batch = read_batch(options, None, batch_observations, ENV)
    epochs = batch_epochs(batch_observations, batch, options)
    parts = [epochs.part(k) for k in range(len(epochs))]
    assert [p.indices for p in parts] == group_by_time(batch_observations)
    for k, part in enumerate(parts):
        uses: dict[int, MeasurementUse] = {}
        candidates, gyros = epoch_parts(part.indices, batch, options, uses)
        assert (part.candidates, part.gyros, part.uses) == (candidates, gyros, uses)
        assert len(candidates) == 3 and len(uses) == 4 and len(gyros) == (k != 2)
        expected = epoch_measurements(candidates, gyros, batch, options)
        for name in (
            "positions",
            "observed",
            "range_std",
            "bearing_std",
            "yaw_rates",
            "gyro_std",
            "averaged",
        ):
            assert np.array_equal(getattr(part.measured, name), getattr(expected, name)), name
        for got, want in zip(part.measured.kernel_arrays, expected.kernel_arrays, strict=True):
            assert np.array_equal(got, want)
            assert type(got) is float or (got.dtype == np.float64 and got.flags.c_contiguous)


def test_gross_outlier_range_fails_the_gate(pipeline) -> None:
    _, state = run(pipeline, started(pipeline), 10, seed=9)
    batch = epoch(11 * DT, np.random.default_rng(10))
    bad = next(i for i, o in enumerate(batch) if isinstance(o, RsuObservation) and o.rsu_id == "N050")
    batch[bad] = dataclasses.replace(batch[bad], range=batch[bad].range + 40.0)
    fixes, _ = pipeline.process(state, batch, ENV)
    use = next(u for u in fixes[0].measurements if u.index == bad)
    assert not use.used and "gate" in use.reason
    assert fixes[0].status == "tracking"
    assert position_error(fixes[0]) < 1.0
    # with the gate and fault exclusion disabled the outlier goes in, drags the estimate and raises the alarm
    options = {"gate_probability": 0.0, "fault_exclusion": False, "integrity": True}
    _, state_nogate = run(pipeline, started(pipeline, options), 10, seed=9)
    fixes_nogate, _ = pipeline.process(state_nogate, batch, ENV)
    assert next(u for u in fixes_nogate[0].measurements if u.index == bad).used
    assert position_error(fixes_nogate[0]) > position_error(fixes[0])
    assert fixes_nogate[0].integrity == "alarm"
    # with the gate disabled fault detection still excludes it
    _, state_excluding = run(
        pipeline, started(pipeline, {"gate_probability": 0.0, "integrity": True}), 10, seed=9
    )
    fixes_excluding, _ = pipeline.process(state_excluding, batch, ENV)
    use = next(u for u in fixes_excluding[0].measurements if u.index == bad)
    assert not use.used and use.reason.startswith("excluded by fault detection")


def test_absurd_gyro_reading_fails_the_gate(pipeline) -> None:
    _, state = run(pipeline, started(pipeline), 10, seed=11)
    batch = epoch(11 * DT, np.random.default_rng(12))
    batch[-1] = GyroObservation(t=batch[-1].t, yaw_rate=3.0)
    fixes, _ = pipeline.process(state, batch, ENV)
    use = fixes[0].measurements[-1]
    assert use.kind == "gyro" and not use.used and "gate" in use.reason


@pytest.mark.parametrize("handling", ["joint", "average"])
@pytest.mark.parametrize("filter_name", ["ckf", "ukf", "ekf"])
def test_joint_and_average_handling_track_with_every_filter(
    pipeline, handling: str, filter_name: str
) -> None:
    fixes, _ = run(
        pipeline, started(pipeline, {"rsu_handling": handling, "filter": filter_name}), 30, seed=13
    )
    assert all(f.status == "tracking" for f in fixes)
    assert max(position_error(f) for f in fixes) < 1.0
    dof = {f.nis_dof for f in fixes}
    assert dof == ({2 * 4 + 1} if handling == "joint" else {2 + 1})


def test_joint_and_average_give_different_estimates(pipeline) -> None:
    joint, _ = run(pipeline, started(pipeline, {"rsu_handling": "joint"}), 10, seed=14)
    average, _ = run(pipeline, started(pipeline, {"rsu_handling": "average"}), 10, seed=14)
    assert max(abs(a.x - b.x) + abs(a.y - b.y) for a, b in zip(joint, average)) > 1e-6


@pytest.mark.parametrize(
    ("override", "option"),
    [({"range_std": 2.5}, {"range_std": 2.5}), ({"bearing_std": 0.03}, {"bearing_std": 0.03})],
)
def test_per_rsu_noise_overrides_are_honoured(pipeline, override: dict, option: dict) -> None:
    """RSUs carrying their own noise level behave exactly as if the option said so for all of them."""
    overridden = StaticEnvironment({k: dataclasses.replace(r, **override) for k, r in ENV.rsus.items()})
    with_override, _ = run(pipeline, started(pipeline), 8, seed=15, env=overridden)
    with_option, _ = run(pipeline, started(pipeline, option), 8, seed=15, env=ENV)
    plain, _ = run(pipeline, started(pipeline), 8, seed=15, env=ENV)
    for a, b in zip(with_override, with_option):
        assert (a.x, a.y, a.position_cov, a.model_probabilities) == (
            b.x,
            b.y,
            b.position_cov,
            b.model_probabilities,
        )
    assert any(a.position_cov != c.position_cov for a, c in zip(with_override, plain))


def test_per_rsu_noise_override_of_one_rsu_changes_its_weight(pipeline) -> None:
    """A very noisy RSU barely moves the estimate: its outlier is absorbed when its range_std is huge."""
    noisy = dict(ENV.rsus)
    noisy["N050"] = dataclasses.replace(noisy["N050"], range_std=50.0, bearing_std=0.5)
    env = StaticEnvironment(noisy)
    _, state = run(pipeline, started(pipeline, {"gate_probability": 0.0}), 10, seed=16, env=env)
    batch = epoch(11 * DT, np.random.default_rng(17), env)
    bad = next(i for i, o in enumerate(batch) if isinstance(o, RsuObservation) and o.rsu_id == "N050")
    batch[bad] = dataclasses.replace(batch[bad], range=batch[bad].range + 20.0)
    fixes, _ = pipeline.process(state, batch, env)
    assert position_error(fixes[0]) < 0.6


def test_per_rsu_radius_override_is_honoured(pipeline) -> None:
    rsus = dict(ENV.rsus)
    rsus["S200"] = dataclasses.replace(rsus["S200"], radius=100.0)
    rsus["FAR"] = dataclasses.replace(rsus["FAR"], radius=5000.0)
    env = StaticEnvironment(rsus)
    batch = epoch(DT, np.random.default_rng(18), env)
    fixes, _ = pipeline.process(started(pipeline, {"max_rsus": 64, "gate_probability": 0.0}), batch, env)
    uses = {
        batch[u.index].rsu_id: u for u in fixes[0].measurements if isinstance(batch[u.index], RsuObservation)
    }
    assert not uses["S200"].used and "100 m" in uses["S200"].reason  # 179 m away, radius 100 m
    assert uses["FAR"].used  # 1979 m away, radius 5000 m
    assert uses["N150"].used  # 132 m, default radius 160 m
    assert not uses["N250"].used and "160 m" in uses["N250"].reason


def test_fix_covariances_are_symmetric_positive_definite(pipeline) -> None:
    fixes, _ = run(pipeline, started(pipeline), 40, seed=19)
    for fix in fixes:
        position_cov = np.array(fix.position_cov)
        assert position_cov.shape == (2, 2)
        np.testing.assert_array_equal(position_cov, position_cov.T)
        assert np.linalg.eigvalsh(position_cov).min() > 0.0
        state_cov = np.array(fix.state_cov)
        assert state_cov.shape == (len(fix.state_components),) * 2
        np.testing.assert_array_equal(state_cov, state_cov.T)
        assert np.linalg.eigvalsh(state_cov).min() > 0.0
        assert abs(sum(fix.model_probabilities.values()) - 1.0) < 1e-12
        assert fix.nis is not None and fix.nis >= 0.0


def test_fixes_are_the_objects_their_constructor_makes(pipeline) -> None:
    """rsu_imu builds its fixes without Fix.__init__ (rsu_imu_fix.FixForm.fix): each must equal the one the
    constructor makes from its fields, with every field set, in the constructor's order, and be read
    from the kinematic block of its own state covariance."""
    fixes, _ = run(pipeline, started(pipeline), 30, seed=23)
    names = [field.name for field in dataclasses.fields(Fix)]
    for fix in fixes:
        assert list(vars(fix)) == names
        assert Fix(**vars(fix)) == fix
        order = [fix.state_components.index(name) for name in ("xp", "yp", "xv", "yv")]
        cov = np.array(fix.state_cov)
        assert fix.kinematic_cov == cov[np.ix_(order, order)].tolist()
        assert fix.position_cov == cov[np.ix_(order[:2], order[:2])].tolist()
        assert (fix.x, fix.y, fix.vx, fix.vy) == tuple(fix.state[k] for k in order)
        assert fix.speed == math.hypot(fix.vx, fix.vy)


# -- state bytes and determinism ---------------------------------------------------------------------
def test_state_reencodes_byte_identically(pipeline) -> None:
    from edgepos.pipelines.plausibility import unwrap, wrap

    _, state = run(pipeline, started(pipeline), 12, seed=20)
    # the registry's pipelines wrap the state: the lag window's envelope (its checkpoints, the current
    # state and the window's observations) around plausibility's around the pipeline's own
    window = lag._unpack(state)
    assert lag._pack(window) == state
    # its base is a checkpoint from before max_delay_s, and it holds every epoch after it: all a measurement
    # late by up to max_delay_s needs filtered again
    assert (
        window.newest == 12 * DT and window.base.t is not None and window.base.t < window.newest - MAX_DELAY
    )
    assert window.times == [t for t in (k * DT for k in range(1, 13)) if t > window.base.t]
    assert [o for record in window.records for o in lag.decode_epoch(record)] == window.observations()
    for inner_state in [window.current, *(c.state for c in window.checkpoints)]:
        envelope, inner = unwrap(inner_state)
        assert wrap(envelope, inner) == inner_state
        assert _decode(inner).to_bytes() == inner
    # an empty batch changes nothing
    fixes, same = pipeline.process(state, [], ENV)
    assert fixes == [] and same == state


def _json_layout(inner: bytes) -> bytes:
    """An rsu_imu state in the layout written before the binary one (``core.state``, JSON header)."""
    session = _decode(inner)
    meta = {
        "pipeline": "rsu_imu",
        "options_json": session.options_key,
        "initialised": session.initialised,
        "t": session.t,
        "filter_t": session.filter_t,
        "epochs": session.epochs,
    }
    arrays = {"probabilities": session.probabilities, "means": session.means, "covs": session.covs}
    return state_format.pack(meta, arrays)


def test_the_binary_state_round_trips_exactly_and_the_json_layout_is_still_read(pipeline) -> None:
    """Every number of the session reads back bit for bit (also before the first epoch: no t, no
    filter_t); a state stored in the former JSON layout decodes to the same session, and a batch applied
    to it answers the same fixes and writes the same bytes as one applied to the binary state."""
    from edgepos.pipelines.plausibility import unwrap, wrap

    fresh = _decode(unwrap(lag._unpack(started(pipeline)).current)[1])
    assert fresh.t is None and fresh.filter_t is None and fresh.epochs == 0
    again = _decode(fresh.to_bytes())
    assert (again.t, again.filter_t, again.initialised, again.options) == (None, None, True, fresh.options)
    assert again.to_bytes() == fresh.to_bytes()
    _, state = run(pipeline, started(pipeline, {"integrity": True}), 6, seed=23)
    envelope, inner = unwrap(lag._unpack(state).current)
    session, legacy = _decode(inner), _decode(_json_layout(inner))
    for name in ("options", "options_key", "initialised", "t", "filter_t", "epochs"):
        assert getattr(legacy, name) == getattr(session, name), name
    for name in ("probabilities", "means", "covs"):
        assert getattr(legacy, name).tobytes() == getattr(session, name).tobytes(), name
    # the JSON layout predates the integrity bank (the binary state's tail): it reads as a session without one
    assert session.integrity_bank is not None and legacy.integrity_bank is None
    without_bank = dataclasses.replace(session, integrity_bank=None).to_bytes()
    assert legacy.to_bytes() == without_bank and inner.startswith(without_bank)
    batch = epoch(7 * DT, np.random.default_rng(7))
    window = lag._unpack(state)
    window.current = wrap(envelope, _json_layout(inner))
    fixes_legacy, after_legacy = pipeline.process(lag._pack(window), batch, ENV)
    window.current = wrap(envelope, without_bank)
    fixes, after = pipeline.process(lag._pack(window), batch, ENV)
    assert fixes_legacy == fixes
    assert lag._unpack(after_legacy).current == lag._unpack(after).current


def test_damaged_binary_states_are_state_format_errors(pipeline) -> None:
    from edgepos.pipelines import rsu_imu
    from edgepos.pipelines.plausibility import unwrap

    _, state = run(pipeline, started(pipeline), 3, seed=24)
    inner = unwrap(lag._unpack(state).current)[1]
    for cut in (
        0,
        3,
        4,
        10,
        rsu_imu._STATE.size - 1,
        rsu_imu._STATE.size + 5,
        len(inner) - 8,
        len(inner) - 1,
    ):
        with pytest.raises(state_format.StateFormatError):
            _decode(inner[:cut])
    with pytest.raises(state_format.StateFormatError):
        _decode(inner + b"\x00")
    with pytest.raises(state_format.StateFormatError, match="version 2"):
        _decode(inner[:4] + bytes([2]) + inner[5:])
    with pytest.raises(state_format.StateFormatError):
        _decode(inner[:5] + bytes([8]) + inner[6:])  # an unknown flag
    key_start = rsu_imu._STATE.size
    with pytest.raises(state_format.StateFormatError):
        _decode(inner[:key_start] + b"[" + inner[key_start + 1 :])  # options text that is not a JSON object
    with pytest.raises(ValueError, match="not finite"):
        session = _decode(inner)
        session.covs[0, 0, 0] = math.nan
        session.to_bytes()


def test_processing_is_deterministic(pipeline) -> None:
    _, state = run(pipeline, started(pipeline), 12, seed=21)
    batch = [o for k in range(13, 20) for o in epoch(k * DT, np.random.default_rng(k))]
    fixes_a, state_a = pipeline.process(state, batch, ENV)
    fixes_b, state_b = pipeline.process(state, batch, ENV)
    assert state_a == state_b
    assert fixes_a == fixes_b


def test_one_batch_equals_epoch_by_epoch(pipeline) -> None:
    """Splitting a stream into batches does not change a single bit of the result: the fixes and the
    filter's state after the last epoch. (Not the whole state bytes: the lag window keeps checkpoints at
    batch boundaries and drops the epochs before the latest one older than max_delay_s, so batchings
    differ in their checkpoints and in how many old epochs they still hold; those they hold are the same.)"""
    rng = np.random.default_rng(22)
    epochs = [epoch(k * DT, rng) for k in range(1, 16)]
    state = started(pipeline)
    fixes_one, state_one = pipeline.process(state, [o for e in epochs for o in e], ENV)
    fixes_many: list[Fix] = []
    for e in epochs:
        new, state = pipeline.process(state, e, ENV)
        fixes_many.extend(new)
    window_many, window_one = lag._unpack(state), lag._unpack(state_one)
    assert window_many.current == window_one.current
    assert window_many.newest == window_one.newest == epochs[-1][0].t
    held = min(len(window_many.times), len(window_one.times))
    assert held >= round(MAX_DELAY / DT)
    assert window_many.times[-held:] == window_one.times[-held:]
    assert window_many.records[-held:] == window_one.records[-held:]
    assert len(fixes_one) == len(fixes_many) == len(epochs)
    for a, b in zip(fixes_one, fixes_many):
        assert (a.t, a.x, a.y, a.vx, a.vy, a.position_cov, a.state_cov, a.model_probabilities, a.nis) == (
            b.t,
            b.x,
            b.y,
            b.vx,
            b.vy,
            b.position_cov,
            b.state_cov,
            b.model_probabilities,
            b.nis,
        )


def test_foreign_or_corrupt_state_is_refused(pipeline) -> None:
    with pytest.raises(state_format.StateFormatError):
        pipeline.process(state_format.pack({"pipeline": "other"}, {}), [], ENV)
    with pytest.raises(state_format.StateFormatError):
        pipeline.process(started(pipeline)[:-3], [], ENV)


# -- gaps in the data ---------------------------------------------------------------------------------
LONG_ROAD = StaticEnvironment(
    {
        f"R{x:04d}": Rsu(f"R{x:04d}", float(x), -4.0 if (x // 50) % 2 == 0 else 15.0)
        for x in range(0, 2001, 50)
    }
)


@pytest.mark.parametrize("gap", [25.0, 30.0])
def test_tracking_resumes_after_a_gap_in_the_data(pipeline, gap: float) -> None:
    """A vehicle that stops reporting for half a minute (a tunnel, lost link) keeps its session: past
    max_gap the pipeline starts again from the RSU measurements (no estimation error, which would repeat
    for ever as the gap only grows) and the estimate re-converges."""
    _, state = run(pipeline, started(pipeline), 10, seed=23, env=LONG_ROAD)
    rng = np.random.default_rng(24)
    fixes: list[Fix] = []
    for k in range(20):
        new, state = pipeline.process(state, epoch(1.0 + gap + k * DT, rng, LONG_ROAD), LONG_ROAD)
        fixes.extend(new)
    assert fixes[0].status == "initialised"
    assert all(f.status == "tracking" for f in fixes[1:])
    assert max(position_error(f) for f in fixes[10:]) < 1.0


@pytest.mark.parametrize("gap", [1e3, 1e6, 1e120])
def test_absurd_gaps_fail_only_with_estimation_errors(pipeline, gap: float) -> None:
    """Whatever finite times a client sends, processing succeeds or raises EstimationError or
    PipelineInputError (both 422; a jump beyond max_time_jump_s is refused), never another exception
    (which the service would turn into a 500)."""
    from edgepos.core.errors import EstimationError

    for filter_name in ("ckf", "ekf"):
        for which in (
            pipeline,
            pipeline.inner.inner,
        ):  # the registry's, and the filter without the time bound
            _, state = run(which, started(which, {"filter": filter_name}), 3, seed=25)
            try:
                which.process(state, epoch(0.3 + gap, np.random.default_rng(26)), ENV)
            except (EstimationError, PipelineInputError):
                pass
