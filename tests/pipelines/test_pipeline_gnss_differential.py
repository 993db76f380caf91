"""gnss_tight with differential corrections from the reference station (tests/data/gnss-rover): better than
without on the split's second half, every pseudorange says whether a correction was added or why not, and
the correction age option is bounded and applied."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from edgepos.core.observations import PseudorangeObservation
from edgepos.eval.gnss_rinex import evaluate
from edgepos.gnss.differential import (
    NO_CORRECTION,
    SYSTEM_NOT_CORRECTED,
    TOO_OLD,
    CorrectionTable,
    base_position,
    corrections_from_epochs,
    epoch_corrections,
)
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.measurements import PseudorangeSet
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs, read_header
from edgepos.pipelines.base import PipelineInputError, StaticEnvironment
from edgepos.pipelines.gnss_satellites import EpochSatellites, leave_out_mixed
from edgepos.pipelines.gnss_tight import GnssTightPipeline

DATA = "tests/data/gnss-rover/"
FILES = (DATA + "rover-0-5min.rnx", DATA + "broadcast-nav.rnx", DATA + "reference-0-5min.csv")
BASE = DATA + "base-0-5min.rnx"
CODES = {s: DEFAULT_CODES[s] for s in "GC"}


def test_the_base_station_makes_the_second_half_better() -> None:
    """UKF, one run from epoch 0 scored on epochs 150-299 (not used for any choice), GPS + BeiDou. The
    corrections themselves (``mixed_corrections`` use: C36, which the base does not track, kept with the
    corrected BeiDou satellites' clock): measured horizontal RMS 3.54 m with the base against 3.68 m without,
    p95 4.93 against 6.01 m; WLS baseline 3.69 against 3.99 m. The thresholds leave margin below the
    measured ratios. With the default (C36 left out; chosen on the first half, where it gives 2.26 against
    2.30 m) the second half is 3.65 m, p95 5.22 m: still better than without the base, by less."""
    options = {"filter": "ukf", "seed": 1}
    without = evaluate(*FILES, "GC", options, score_epochs=(150, 300))
    with_base = evaluate(
        *FILES, "GC", {**options, "mixed_corrections": "use"}, score_epochs=(150, 300), base_path=BASE
    )
    assert with_base["fixes"] == without["fixes"] == 150
    assert with_base["base"]["corrections"] > 3000 and without["base"] is None
    assert with_base["horizontal_rms_m"] < 0.98 * without["horizontal_rms_m"]
    assert with_base["horizontal_p95_m"] < 0.92 * without["horizontal_p95_m"]
    assert with_base["baseline"]["horizontal_rms_m"] < 0.97 * without["baseline"]["horizontal_rms_m"]
    default = evaluate(*FILES, "GC", options, score_epochs=(150, 300), base_path=BASE)
    assert default["horizontal_rms_m"] < without["horizontal_rms_m"]
    assert default["horizontal_p95_m"] < 0.92 * without["horizontal_p95_m"]


def _batches(count: int) -> list[list[PseudorangeObservation]]:
    batches = []
    for epoch in list(read_epochs(FILES[0], CODES))[:count]:
        tow = epoch.gpst % 604800.0
        batches.append(
            [
                PseudorangeObservation(tow, s, int(p), float(pr), float(cn0))
                for s, p, pr, cn0 in zip(epoch.systems, epoch.prns, epoch.pseudorange_m, epoch.cn0_dbhz)
                if np.isfinite(pr) and np.isfinite(cn0)
            ]
        )
    return batches


@pytest.fixture(scope="module")
def ephemerides() -> Ephemerides:
    return Ephemerides.from_navigation(read_navigation(FILES[1]))


def _run(ephemerides: Ephemerides, table, batches, options=None):
    pipeline = GnssTightPipeline()
    state = pipeline.create(
        pipeline.resolve_options({"filter": "ukf", "systems": ["C", "G"], **(options or {})}), None
    )
    environment = StaticEnvironment(navigation=ephemerides, differential=table)
    fixes = []
    for batch in batches:
        out, state = pipeline.process(state, batch, environment)
        fixes.extend(out)
    return fixes


def test_every_pseudorange_says_whether_it_was_corrected(ephemerides: Ephemerides) -> None:
    """With corrections each pseudorange reports correction_applied and, when false, why (C36 and G06 have
    no correction at the base: MARE tracks no C36 B1I and sees G06 below its mask); without, both are
    None."""
    station = base_position(read_header(BASE))
    table = corrections_from_epochs(
        read_epochs(BASE, CODES), station, ephemerides.orbits, ephemerides.atmosphere, CODES
    )
    batches = _batches(5)
    fixes = _run(ephemerides, table, batches)
    applied = reasons = 0
    for fix, batch in zip(fixes, batches):
        for use in fix.measurements:
            assert use.correction_applied is not None
            sat = f"{batch[use.index].system}{batch[use.index].prn:02d}"
            if use.correction_applied:
                applied += 1
                assert use.correction_reason is None
            else:
                reasons += 1
                assert use.correction_reason
                if sat in ("C36", "G06"):
                    assert use.correction_reason.startswith(NO_CORRECTION)
    assert applied > 40 and reasons >= 5
    plain = _run(ephemerides, None, batches)
    assert all(
        u.correction_applied is None and u.correction_reason is None for f in plain for u in f.measurements
    )


def test_stale_corrections_are_not_applied(ephemerides: Ephemerides) -> None:
    """Corrections of the base's first 5 epochs only: 40 s later, from a source whose maximum age is 30 s,
    none applies and each says it is too old; from one of 60 s they apply."""
    station = base_position(read_header(BASE))
    first = list(read_epochs(BASE, CODES))[:5]
    batches = _batches(45)
    for max_age, applies in ((30.0, False), (60.0, True)):
        table = corrections_from_epochs(
            first, station, ephemerides.orbits, ephemerides.atmosphere, CODES, max_age_s=max_age
        )
        last = _run(ephemerides, table, batches, {})[-1]
        applied = sum(bool(u.correction_applied) for u in last.measurements)
        stale = [
            u for u in last.measurements if u.correction_reason and u.correction_reason.startswith(TOO_OLD)
        ]
        if applies:
            assert applied > 10 and not stale
        else:
            assert applied == 0 and len(stale) > 10
            assert f"the maximum correction age {max_age:g} s" in stale[0].correction_reason


@pytest.mark.parametrize("value", [0.0, 601.0, math.nan])
def test_the_maximum_correction_age_is_bounded(value: float) -> None:
    with pytest.raises(ValueError, match="maximum correction age"):
        CorrectionTable([], max_age_s=value)


def test_an_uncorrected_satellite_no_longer_pulls_the_fix_by_its_constellations_offset(
    ephemerides: Ephemerides,
) -> None:
    """A constellation with corrected and uncorrected satellites: every BeiDou correction of the base moved
    by 6 m, as a different median model error at the base would move them. The corrected BeiDou
    satellites' common clock absorbs it; C36, which the base does not track, would sit 6 m further from
    that clock. With mixed_corrections exclude (the default) C36's range is left out, saying why, and the
    fixes do not move (measured 1e-8 m; the least-squares start leaves it out too); with use they move
    (measured: up to 0.89 m over 25 epochs, UKF)."""
    station = base_position(read_header(BASE))
    epochs = [
        epoch_corrections(e, station, ephemerides.orbits, ephemerides.atmosphere, CODES)
        for e in list(read_epochs(BASE, CODES))[:30]
    ]
    shifted = [
        dataclasses.replace(
            e, correction_m=e.correction_m + np.array([6.0 if s[0] == "C" else 0.0 for s in e.sats])
        )
        for e in epochs
    ]
    batches = _batches(25)
    moved = {}
    for mode in ("exclude", "use"):
        fixes = _run(ephemerides, CorrectionTable(epochs), batches, {"mixed_corrections": mode})
        offset = _run(ephemerides, CorrectionTable(shifted), batches, {"mixed_corrections": mode})
        moved[mode] = max(math.hypot(a.x - b.x, a.y - b.y) for a, b in zip(fixes, offset))
        c36 = [
            use
            for fix, batch in zip(fixes, batches)
            for use in fix.measurements
            if (batch[use.index].system, batch[use.index].prn) == ("C", 36)
        ]
        assert c36 and all(use.correction_applied is False for use in c36)
        if mode == "exclude":
            assert all(not use.used and "no differential correction while" in use.reason for use in c36)
    assert moved["exclude"] < 1e-3
    assert moved["use"] > 0.1


def _epoch(systems: str, corrected: list[bool] | None) -> EpochSatellites:
    n = len(systems)
    prs = PseudorangeSet(
        0.0,
        tuple(systems),
        np.arange(1, n + 1),
        np.full(n, 2.2e7),
        np.full(n, 40.0),
        np.ones((n, 3)),
        np.zeros(n),
        np.full(n, 1.57542e9),
    )
    return EpochSatellites(
        prs, list(range(10, 10 + n)), {}, [], None if corrected is None else np.array(corrected)
    )


def test_only_uncorrected_rows_of_a_constellation_with_two_corrected_are_left_out() -> None:
    """GPS: two corrected, one not -> that one out, with its reason; BeiDou: one corrected, one not -> both
    kept (one corrected row only fixes its clock); Galileo: none corrected -> kept; rows not passed
    (below the mask) neither count nor are judged; without corrections nothing changes."""
    satellites = _epoch("GGGCCEEG", [True, True, False, True, False, False, False, False])
    uses: dict = {}
    rows = np.arange(7)  # the last GPS row is below the mask
    kept = leave_out_mixed(satellites, rows, uses)
    assert kept.tolist() == [0, 1, 3, 4, 5, 6]
    assert list(uses) == [12] and not uses[12].used
    assert uses[12].reason.startswith("no differential correction while 2 G satellites have one")
    assert leave_out_mixed(satellites, np.array([0, 2, 3, 4]), {}).tolist() == [0, 2, 3, 4]  # one G corrected
    assert leave_out_mixed(_epoch("GGG", None), np.arange(3), {}).tolist() == [0, 1, 2]


def test_sessions_stored_before_the_option_use_every_satellite(ephemerides: Ephemerides) -> None:
    """A session whose stored options have no mixed_corrections keeps C36 (as mixed_corrections use)."""
    station = base_position(read_header(BASE))
    table = corrections_from_epochs(
        list(read_epochs(BASE, CODES))[:12], station, ephemerides.orbits, ephemerides.atmosphere, CODES
    )
    batches = _batches(10)
    pipeline = GnssTightPipeline()
    resolved = pipeline.resolve_options({"filter": "ukf", "systems": ["C", "G"]})
    del resolved["mixed_corrections"]
    state = pipeline.create(resolved, None)
    environment = StaticEnvironment(navigation=ephemerides, differential=table)
    older = []
    for batch in batches:
        out, state = pipeline.process(state, batch, environment)
        older.extend(out)
    use = _run(ephemerides, table, batches, {"mixed_corrections": "use"})
    assert [f.latitude for f in older] == [f.latitude for f in use]
    assert [[u.used for u in f.measurements] for f in older] == [
        [u.used for u in f.measurements] for f in use
    ]


def test_correction_systems_leaves_the_other_constellations_uncorrected(ephemerides: Ephemerides) -> None:
    """With ``correction_systems`` ["G"] only GPS pseudoranges take the base's corrections; BeiDou ones are
    used uncorrected and say why. The option is bounded to the known constellations."""
    station = base_position(read_header(BASE))
    table = corrections_from_epochs(
        read_epochs(BASE, CODES), station, ephemerides.orbits, ephemerides.atmosphere, CODES
    )
    batches = _batches(5)
    fixes = _run(ephemerides, table, batches, {"correction_systems": ["G"]})
    seen = {"G": 0, "C": 0}
    for fix, batch in zip(fixes, batches):
        for use in fix.measurements:
            system = batch[use.index].system
            seen[system] += 1
            if system == "C":
                assert use.correction_applied is False
                assert use.correction_reason == SYSTEM_NOT_CORRECTED
            elif use.correction_applied is False:
                assert use.correction_reason != SYSTEM_NOT_CORRECTED
    assert seen["G"] > 20 and seen["C"] > 20
    assert sum(u.correction_applied is True for f in fixes for u in f.measurements) > 20
    with pytest.raises(PipelineInputError):
        GnssTightPipeline().resolve_options({"correction_systems": ["R"]})


def test_the_vehicles_galileo_group_delay_is_the_second_halfs_gain() -> None:
    """The station's Leica fits the Galileo ICD's group delay, the vehicle's mosaic-X5 fits none
    (``galileo_group_delay``, chosen on the first half; docs/gnss.md). On the second half, not used for the
    choice, the UKF with the carrier and every constellation corrected gives 2.28 m with none against
    3.25 m with broadcast (measured; the WLS baseline 3.35 against 3.98 m): what ``correction_systems``
    GC had hidden by leaving the Galileo corrections out."""
    options = {"filter": "ukf", "seed": 1}
    broadcast = evaluate(
        *FILES,
        "GCE",
        {**options, "galileo_group_delay": "broadcast"},
        score_epochs=(150, 300),
        base_path=BASE,
        carrier=True,
    )
    none = evaluate(*FILES, "GCE", options, score_epochs=(150, 300), base_path=BASE, carrier=True)
    assert none["fixes"] == broadcast["fixes"] == 150
    assert none["horizontal_rms_m"] < 0.8 * broadcast["horizontal_rms_m"]
    assert none["baseline"]["horizontal_rms_m"] < 0.9 * broadcast["baseline"]["horizontal_rms_m"]
