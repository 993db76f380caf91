"""Time-differenced carrier phase (gnss/tdcp.py): on simulated phases of a receiver on a straight line the
fit gives the displacement and the clock change of the closed form; a slip or a loss of lock on one
satellite drops only that satellite's difference; the phase history round-trips its parts exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.gnss.geodesy import geodetic_to_ecef
from edgepos.gnss.orbits import SPEED_OF_LIGHT, sagnac_range
from edgepos.gnss.tdcp import PhaseHistory, TdcpConfig, displacement, model_terms

WAVELENGTH = SPEED_OF_LIGHT / 1575.42e6
RECEIVER = np.array(geodetic_to_ecef(math.radians(41.64), math.radians(2.35), 250.0), dtype=float)
VELOCITY = np.array([8.0, -11.0, 0.5])
"""The receiver's straight line (ECEF m/s): 13.6 m/s."""
CLOCK_RATE_M_PER_S = 37.0
"""The receiver clock's drift (m/s)."""


def _satellites(t: float) -> tuple[np.ndarray, np.ndarray]:
    """Eight satellites on circular orbits at GPS height spread over the sky above the receiver, and their
    clocks (s, drifting)."""
    up = RECEIVER / np.linalg.norm(RECEIVER)
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    north = np.cross(up, east)
    positions, clocks = [], []
    for k in range(8):
        elevation = math.radians(15.0 + 9.0 * k)
        azimuth = math.radians(47.0 * k) + 1.4e-4 * t
        direction = math.cos(elevation) * (math.sin(azimuth) * east + math.cos(azimuth) * north)
        direction += math.sin(elevation) * up
        positions.append(RECEIVER + 2.2e7 * direction + 900.0 * t * np.cross(up, direction))
        clocks.append(1e-4 * (k - 4) + 1e-9 * k * t)
    return np.array(positions), np.array(clocks)


def _epoch(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The receiver, the satellites, their clocks, the phases (cycles, an ambiguity per satellite) and the
    atmosphere's delays at time t."""
    receiver = RECEIVER + VELOCITY * t
    positions, clocks = _satellites(t)
    k = np.arange(8)
    tropo = 2.4 + 0.1 * k + 0.01 * t * (1.0 + 0.3 * k)  # each changing at its own rate: a sign error
    iono = 3.0 + 0.2 * k - 0.004 * t * (1.0 + 0.5 * k)  # would not hide in the clock change
    ambiguity = np.arange(8) * 1234567.0
    rho = sagnac_range(positions, receiver)
    phase_m = rho - SPEED_OF_LIGHT * clocks + tropo - iono + CLOCK_RATE_M_PER_S * t
    return receiver, positions, clocks, phase_m / WAVELENGTH + ambiguity, np.stack([tropo, iono])


SATS = tuple(f"G{k + 1:02d}" for k in range(8))


def _history(t: float) -> PhaseHistory:
    receiver, positions, clocks, cycles, (tropo, iono) = _epoch(t)
    terms = model_terms(receiver, positions, clocks, tropo, iono, SPEED_OF_LIGHT)
    x, y, z = (float(v) for v in receiver)
    return PhaseHistory(t, (x, y, z), SATS, np.column_stack((cycles, terms)))


def _fit(t0: float, t1: float, cycles_change: np.ndarray | None = None, lli: np.ndarray | None = None):
    history = _history(t0)
    _, positions, clocks, cycles, (tropo, iono) = _epoch(t1)
    if cycles_change is not None:
        cycles = cycles + cycles_change
    terms = model_terms(np.array(history.receiver), positions, clocks, tropo, iono, SPEED_OF_LIGHT)
    elevation = np.radians(15.0 + 9.0 * np.arange(8))
    return displacement(
        history,
        t1,
        SATS,
        cycles,
        np.full(8, WAVELENGTH),
        positions,
        terms,
        elevation,
        np.full(8, np.nan),
        np.zeros(8, dtype=int) if lli is None else lli,
        TdcpConfig(),
    )


def test_the_differences_give_the_straight_lines_displacement_and_clock_change() -> None:
    fit = _fit(10.0, 11.0)
    assert fit.d is not None and fit.cov is not None and fit.why is None
    assert fit.reasons == [None] * 8
    # the closed form: the line's step and the clock's change (exact phases; the fit's linearisation of
    # the range and the Sagnac term leave micrometres)
    assert np.max(np.abs(fit.d - VELOCITY)) < 1e-4
    assert abs(fit.clock_m - CLOCK_RATE_M_PER_S) < 1e-4
    assert np.all(np.linalg.eigvalsh(fit.cov) > 0.0)
    assert np.allclose(fit.cov, fit.cov.T)
    # two seconds: twice the step (27 m; the linearisation leaves 0.1 mm, under the phase's noise)
    longer = _fit(10.0, 12.0)
    assert longer.d is not None and np.max(np.abs(longer.d - 2.0 * VELOCITY)) < 1e-3


def test_a_slip_on_one_satellite_drops_only_its_difference() -> None:
    change = np.zeros(8)
    change[3] = 5.0  # five cycles, 0.95 m, no loss-of-lock flag and no Doppler to catch it
    fit = _fit(10.0, 11.0, change)
    assert fit.d is not None
    assert fit.reasons[3] is not None and "off the displacement fit" in fit.reasons[3]
    assert [r for k, r in enumerate(fit.reasons) if k != 3] == [None] * 7
    assert np.max(np.abs(fit.d - VELOCITY)) < 1e-4
    # the loss-of-lock flag drops the satellite before the fit
    lli = np.zeros(8, dtype=int)
    lli[5] = 1
    flagged = _fit(10.0, 11.0, lli=lli)
    assert flagged.reasons[5] == "loss of lock (lli bit 0)"
    assert [r for k, r in enumerate(flagged.reasons) if k != 5] == [None] * 7
    assert flagged.d is not None and np.max(np.abs(flagged.d - VELOCITY)) < 1e-4


def test_too_few_continuous_phases_give_no_displacement() -> None:
    lli = np.array([1, 1, 1, 1, 0, 0, 0, 0])
    fit = _fit(10.0, 11.0, lli=lli)
    assert fit.d is None and fit.cov is None and fit.why == "4 continuous carrier phases"
    assert fit.reasons[:4] == ["loss of lock (lli bit 0)"] * 4
    assert all("fewer than 5" in str(r) for r in fit.reasons[4:])
    gap = _fit(10.0, 16.0)  # beyond the 5 s the differences may span
    assert gap.d is None and all("max gap 5 s" in str(r) for r in gap.reasons)


def test_the_history_round_trips_its_parts_exactly() -> None:
    history = _history(10.0)
    head, sats, table = history.to_parts()
    again = PhaseHistory.from_parts(head, sats, table.copy())
    assert again == history
    assert PhaseHistory.from_parts(*PhaseHistory().to_parts()) == PhaseHistory()
    with pytest.raises(ValueError):
        PhaseHistory.from_parts(None, sats, table)
    with pytest.raises(ValueError):
        PhaseHistory.from_parts(head[:3], sats, table)
    with pytest.raises(ValueError):
        PhaseHistory.from_parts(head, sats[:-1], table)
