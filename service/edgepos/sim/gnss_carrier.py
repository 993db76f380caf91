"""Simulated carrier phase of the street-canyon scenario's signals: lock, cycle slips and errors.

The phase of satellite j (cycles, RINEX convention: it grows with the range) is

    L = (rho + b_sys - c dts_j - I_j + T_j + e_sisre,j + m_phi,j + n_phi,j + nlos_j) / lambda + N_j

the pseudorange's terms with the ionosphere's sign turned (it advances the phase), the code's multipath
and noise replaced by the carrier's, and N_j an integer ambiguity drawn whenever the carrier loop locks.
A reflected (NLOS) signal's phase follows the reflected path, so it carries the same extra delay as its
code.

Lock is a two-state chain per satellite whose rates are measured on the real recording
(``tests/data/gnss-rover``, the Septentrio rover in the street, all 300 epochs; ``phase_lock_table``):
the fraction of pseudoranges that carry a phase by C/N0 (0.04 below 25 dB-Hz up to 0.90 above 45) and
the loss-of-lock indicator's rate per phase epoch (1.5-9 %). A locked satellite loses lock with the LLI
rate ``p``; an unlocked one (whose code is tracked) locks with ``p a / (1 - a)`` for the phase fraction
``a``, so that ``a`` is the chain's stationary share. Each new lock draws a new ambiguity and sets LLI
bit 0. While locked, an unflagged cycle slip of 1-20 cycles happens with ``unflagged_slip_probability``
per epoch (the recording's Doppler test caught 15 slips LLI did not flag in 1724 phases of its first
half, 0.9 %, some of them perhaps not slips: half of it is used).

The carrier's errors: thermal noise lambda / (2 pi) sqrt(B / (C/N0)) with a 10 Hz loop bandwidth (half a
millimetre at 45 dB-Hz), and multipath ``phase_multipath_m`` times the code multipath's unit
Gauss-Markov series (the same reflections; a carrier's multipath is bounded by a quarter wavelength, about
5 cm, and centimetres in practice).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edgepos.gnss.orbits import SPEED_OF_LIGHT

PHASE_LOCK_CN0_DBHZ = np.array([22.5, 27.5, 32.5, 37.5, 42.5, 50.0])
"""C/N0 bin centres of the recording's figures (bins 0-25, 25-30, ..., 45-60 dB-Hz)."""
PHASE_FRACTION = np.array([0.04, 0.15, 0.44, 0.64, 0.78, 0.90])
"""Share of the recording's pseudoranges with a carrier phase, per bin (441 ... 1709 pseudoranges a bin)."""
LOSS_OF_LOCK_RATE = np.array([0.044, 0.044, 0.063, 0.094, 0.042, 0.015])
"""LLI bit 0 per phase epoch on the recording, per bin (the two lowest bins pooled: 5 of 113)."""


@dataclass(frozen=True)
class CarrierModel:
    """The carrier loop's lock, slips and errors (see the module docstring for where each comes from)."""

    loop_bandwidth_hz: float = 10.0
    phase_multipath_m: float = 0.01
    unflagged_slip_probability: float = 0.0045
    slip_cycles: tuple[int, int] = (1, 20)


@dataclass(frozen=True)
class CarrierPhase:
    """(K, n) carrier phase in cycles (NaN where the loop holds no lock) and the RINEX LLI (0 or 1)."""

    cycles: np.ndarray
    lli: np.ndarray


@dataclass(frozen=True)
class CarrierDraws:
    """The random numbers of a run's carrier, drawn once in a fixed order (see :func:`draw`)."""

    noise: np.ndarray
    lock: np.ndarray
    ambiguity: np.ndarray
    slip: np.ndarray
    slip_size: np.ndarray
    slip_sign: np.ndarray


def draw(rng: np.random.Generator, shape: tuple[int, int], model: CarrierModel) -> CarrierDraws:
    """Every random number the carrier needs for ``shape`` = (epochs, satellites)."""
    low, high = model.slip_cycles
    return CarrierDraws(
        noise=rng.standard_normal(shape),
        lock=rng.uniform(size=shape),
        ambiguity=rng.integers(-100_000, 100_000, shape).astype(float),
        slip=rng.uniform(size=shape),
        slip_size=rng.integers(low, high + 1, shape).astype(float),
        slip_sign=rng.choice([-1.0, 1.0], shape),
    )


def lock_rates(cn0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per C/N0 (dB-Hz): the probability of losing lock in an epoch and of locking in one (unlocked)."""
    fraction = np.interp(cn0, PHASE_LOCK_CN0_DBHZ, PHASE_FRACTION)
    loss = np.interp(cn0, PHASE_LOCK_CN0_DBHZ, LOSS_OF_LOCK_RATE)
    return loss, np.minimum(loss * fraction / (1.0 - fraction), 1.0)


def carrier_phase(
    draws: CarrierDraws,
    model: CarrierModel,
    tracked: np.ndarray,
    cn0: np.ndarray,
    path_m: np.ndarray,
    multipath_unit: np.ndarray,
    frequency_hz: np.ndarray,
) -> CarrierPhase:
    """The phase of every tracked signal at every epoch. ``path_m`` (K, n) is the phase's path in metres
    before its own multipath and noise (range, clocks, atmosphere with the ionosphere advanced, orbit
    error, the NLOS extra delay); ``multipath_unit`` the code multipath's unit series; ``frequency_hz`` (n,)."""
    epochs, sats = tracked.shape
    wavelength = SPEED_OF_LIGHT / frequency_hz
    thermal = wavelength[None, :] / (2.0 * math.pi) * np.sqrt(model.loop_bandwidth_hz / 10.0 ** (cn0 / 10.0))
    metres = path_m + model.phase_multipath_m * multipath_unit + thermal * draws.noise
    loss, acquire = lock_rates(cn0)
    cycles = np.full((epochs, sats), np.nan)
    lli = np.zeros((epochs, sats), dtype=int)
    locked = np.zeros(sats, dtype=bool)
    ambiguity = np.zeros(sats)
    for k in range(epochs):
        keeps = locked & tracked[k] & (draws.lock[k] >= loss[k])
        locks = ~locked & tracked[k] & (draws.lock[k] < acquire[k])
        ambiguity[locks] = draws.ambiguity[k, locks]
        lli[k, locks] = 1
        slips = keeps & (draws.slip[k] < model.unflagged_slip_probability)
        ambiguity[slips] += draws.slip_sign[k, slips] * draws.slip_size[k, slips]
        locked = keeps | locks
        cycles[k, locked] = metres[k, locked] / wavelength[locked] + ambiguity[locked]
    return CarrierPhase(cycles, lli)
