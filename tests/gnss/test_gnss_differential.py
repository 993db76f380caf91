"""Differential corrections (gnss/differential.py) on the reference station's five minutes
(tests/data/gnss-rover/base-0-5min.rnx): injected errors come back as corrections, the corrections put the
station back at its own position, and the age and ephemeris-issue rules each refuse a correction."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from edgepos.gnss.differential import (
    ISSUE_MISMATCH,
    NO_CORRECTION,
    TOO_OLD,
    Correction,
    CorrectionTable,
    EpochCorrections,
    apply_corrections,
    base_position,
    correct_set,
    corrections_from_epochs,
    epoch_corrections,
)
from edgepos.gnss.geodesy import ecef_to_geodetic, enu_rotation
from edgepos.gnss.measurements import Atmosphere, prepare_epoch
from edgepos.gnss.orbits import SPEED_OF_LIGHT, BroadcastOrbits, sagnac_range
from edgepos.gnss.rinex_nav import NavigationData
from edgepos.gnss.rinex_obs import DEFAULT_CODES, ObservationEpoch, read_epochs, read_header
from edgepos.gnss.spp import solve_epoch

BASE = "tests/data/gnss-rover/base-0-5min.rnx"
CODES = {s: DEFAULT_CODES[s] for s in "GC"}


@pytest.fixture(scope="module")
def base_epochs() -> list[ObservationEpoch]:
    return list(read_epochs(BASE, CODES))


@pytest.fixture(scope="module")
def station() -> np.ndarray:
    return base_position(read_header(BASE))


def test_station_position_is_the_marker_plus_the_antenna_height() -> None:
    """MARE's header: marker at APPROX POSITION XYZ, antenna reference point 0.077 m above it (H/E/N)."""
    header = read_header(BASE)
    assert header.antenna_delta_hen == (0.077, 0.0, 0.0)
    marker = np.array(header.approx_position)
    offset = base_position(header) - marker
    lat, lon, _ = ecef_to_geodetic(marker)
    enu = enu_rotation(float(lat), float(lon)) @ offset
    np.testing.assert_allclose(enu, [0.0, 0.0, 0.077], atol=1e-9)
    with pytest.raises(ValueError, match="APPROX POSITION XYZ"):
        base_position(dataclasses.replace(header, approx_position=None))


def test_correction_is_model_minus_measured_with_the_clock_removed(
    base_epochs: list[ObservationEpoch], station: np.ndarray, orbits: BroadcastOrbits, nav: NavigationData
) -> None:
    """Pseudoranges built as the model at the station plus a receiver clock of 30 km plus known errors per
    satellite: each correction is minus its error plus its system's median error (the clock estimate
    absorbs the median)."""
    atmosphere = Atmosphere.from_navigation(nav)
    epoch = base_epochs[0]
    rng = np.random.default_rng(3)
    errors = rng.normal(0.0, 3.0, len(epoch))
    pseudoranges = epoch.pseudorange_m.copy()
    for _ in range(4):  # the transmit time depends on the pseudorange: iterate to the fixed point
        built = dataclasses.replace(epoch, pseudorange_m=pseudoranges)
        prs, dropped = prepare_epoch(built, orbits, CODES)
        assert not dropped
        iono, tropo, _, _ = atmosphere.delays(station, prs)
        model = sagnac_range(prs.sat_position, station) + iono + tropo - SPEED_OF_LIGHT * prs.sat_clock_s
        pseudoranges = model + 30_000.0 + errors
    built = dataclasses.replace(epoch, pseudorange_m=pseudoranges)
    result = epoch_corrections(built, station, orbits, atmosphere, CODES)
    prs, _ = prepare_epoch(built, orbits, CODES)
    _, _, elevation, _ = atmosphere.delays(station, prs)
    kept = elevation >= np.radians(10.0)
    assert result.sats == tuple(s for s, k in zip(prs.sats, kept) if k)
    systems = np.array(prs.systems)
    expected = {}
    for system in set(prs.systems):
        rows = kept & (systems == system)
        for sat, error in zip(np.array(prs.sats)[rows], errors[rows]):
            expected[sat] = -error + np.median(errors[rows])
    np.testing.assert_allclose(result.correction_m, [expected[s] for s in result.sats], atol=1e-6)
    assert all(issue[1] > 0 for issue in result.issues)


def test_corrections_put_the_station_back_at_its_position(
    base_epochs: list[ObservationEpoch], station: np.ndarray, orbits: BroadcastOrbits, nav: NavigationData
) -> None:
    """Closed loop on the real file: the station's own observations with its corrections solve to its
    known position (every 10th epoch, starting 1 km away), far below a metre; uncorrected they do not."""
    atmosphere = Atmosphere.from_navigation(nav)
    sample = base_epochs[::10]
    table = corrections_from_epochs(sample, station, orbits, atmosphere, CODES)
    lat, lon, _ = ecef_to_geodetic(station)
    rotation = enu_rotation(float(lat), float(lon))
    raw_errors = []
    for epoch in sample:
        prs, _ = prepare_epoch(epoch, orbits, CODES)
        corrected, applied, reasons = correct_set(prs, orbits, table, 30.0)
        assert applied.sum() >= 8
        assert all((r is None) == a for r, a in zip(reasons, applied))
        solution = solve_epoch(corrected.subset(applied), atmosphere, initial=station + 1000.0)
        assert np.linalg.norm(solution.position - station) < 0.01
        raw = solve_epoch(prs, atmosphere, initial=station + 1000.0)
        raw_errors.append(np.hypot(*(rotation @ (raw.position - station))[:2]))
    assert max(raw_errors) > 0.5  # the corrections had something to remove


def _table(gpst: float = 1000.0) -> CorrectionTable:
    return CorrectionTable(
        [EpochCorrections(gpst, ("G05",), np.array([2.5]), ((45, 900.0),), np.array([4.0]), np.array([2.4]))]
    )


def test_age_rule() -> None:
    """A correction applies from its base epoch to max_age_s after it; never before it (no future base
    epoch is used); a satellite without any gets none."""
    table = _table()
    fresh = table.lookup("G05", (45, 900.0), 1010.0, 30.0)
    assert isinstance(fresh, Correction) and fresh.value_m == 2.5 and fresh.age_s == pytest.approx(10.0)
    assert isinstance(table.lookup("G05", (45, 900.0), 1030.0, 30.0), Correction)
    stale = table.lookup("G05", (45, 900.0), 1030.5, 30.0)
    assert isinstance(stale, str) and stale.startswith(TOO_OLD) and "30.5 s" in stale
    early = table.lookup("G05", (45, 900.0), 999.0, 30.0)
    assert isinstance(early, str) and early.startswith(NO_CORRECTION)
    assert table.lookup("G07", (45, 900.0), 1010.0, 30.0) == NO_CORRECTION


def test_ephemeris_issue_rule(orbits: BroadcastOrbits, base_epochs: list[ObservationEpoch]) -> None:
    """A correction computed with another ephemeris (IODE or toe) is not applied, and says which."""
    table = _table()
    for other in ((46, 900.0), (45, 8100.0), None):
        found = table.lookup("G05", other, 1010.0, 30.0)
        assert isinstance(found, str) and found.startswith(ISSUE_MISMATCH) and "IODE 45" in found
    # On the real file: a rover epoch whose ephemeris differs from the table's gets no correction.
    epoch = base_epochs[0]
    prs, _ = prepare_epoch(epoch, orbits, CODES)
    atmosphere = Atmosphere(None)
    real = epoch_corrections(epoch, base_position(read_header(BASE)), orbits, atmosphere, CODES)
    shifted = CorrectionTable(
        [dataclasses.replace(real, issues=tuple((iode + 1, toe) for iode, toe in real.issues))]
    )
    _, applied, reasons = correct_set(prs, orbits, shifted, 30.0)
    assert not applied.any()
    assert all(r is not None and r.startswith((ISSUE_MISMATCH, NO_CORRECTION)) for r in reasons)
    assert sum(r.startswith(ISSUE_MISMATCH) for r in reasons if r) == len(real.sats)


def test_unmodelled_atmosphere_takes_the_base_delays() -> None:
    """A rover that models no ionosphere / troposphere adds the base's modelled delays to the correction."""
    table = _table()
    delta, reasons = apply_corrections(table, ["G05"], [(45, 900.0)], 1000.0, 30.0, False, False)
    assert reasons == [None] and delta[0] == pytest.approx(2.5 + 4.0 + 2.4)
    delta, _ = apply_corrections(table, ["G05"], [(45, 900.0)], 1000.0, 30.0, True, True)
    assert delta[0] == pytest.approx(2.5)
