"""Simulated Doppler of the street-canyon scenario's signals: the range rate with its errors, and the
satellite velocity and clock drift a client sends with it.

The range rate of satellite j (m/s) is the time derivative of the pseudorange's geometry and clocks,

    rho_dot = u_j . (Rz(omega_e tau) v_j - v_r) + d - c dts_dot_j + nlos_dot_j + n_j

with u_j the unit line of sight of the rotated satellite position (as the pseudorange's), v_j the
satellite's Earth-fixed velocity at transmit time (``Constellation.ecef_velocity_each``), v_r the
vehicle's velocity, d the receiver clock drift (m/s, the integrated random walk the pseudorange's bias
integrates), dts_dot_j the satellite clock drift, nlos_dot_j the rate of a reflected signal's extra path
and n_j the loop's noise; the receiver reports D = -rho_dot / lambda (RINEX sign). The rates of the
atmosphere (millimetres per second) and of the code multipath are left out.

The noise's standard deviation by C/N0 is measured on the real recording (``tests/data/gnss-rover``, all
300 epochs, ``python -m edgepos.gnss.doppler_residuals --epochs 0:300``): the robust std (1.4826 x the
median absolute residual at the reference trajectory) of 0.515, 0.133, 0.069 and 0.031 m/s in the C/N0
bands 0-35, 35-42, 42-48 and 48-100 dB-Hz (1555, 1391, 2149 and 207 Dopplers), placed at 30, 38.5, 45
and 50 dB-Hz and interpolated in log std (thermal noise falls by 10^(dC/N0 / 20): 6.5 dB between the
middle bands gives the measured factor 1.9 against 2.1). The recording's RMS is larger (0.67 m/s against a
robust 0.12) because of its reflected signals; here those carry their own extra path's rate instead.

A reflected signal's extra path ``2 d cos(el) |sin(az - street axis)|`` (the specular term of
``sim.gnss_sensors``) changes as the satellite moves and the vehicle turns; its rate is the path's
difference between neighbouring GNSS epochs of the same place (central where both neighbours share the
place, one-sided where one does, zero for a lone epoch): across a change of place the reflector changes,
and the path's jump is no rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edgepos.gnss.orbits import SPEED_OF_LIGHT

DOPPLER_CN0_DBHZ = np.array([30.0, 38.5, 45.0, 50.0])
"""C/N0 (dB-Hz) at which the recording's Doppler noise was measured (band 0-35 placed at 30, 48-100 at 50)."""
DOPPLER_STD_MPS = np.array([0.515, 0.133, 0.069, 0.031])
"""The recording's robust std of the range rate (m/s) per band (see the module docstring)."""


@dataclass(frozen=True)
class DopplerModel:
    """The Doppler's noise (scaled from the recording's by ``noise_scale``) and whether reflected signals
    carry their extra path's rate."""

    noise_scale: float = 1.0
    reflected_rate: bool = True


def noise_std(cn0: np.ndarray) -> np.ndarray:
    """Range-rate noise std (m/s) at C/N0 (dB-Hz), held flat outside the measured bands."""
    result: np.ndarray = np.exp(np.interp(cn0, DOPPLER_CN0_DBHZ, np.log(DOPPLER_STD_MPS)))
    return result


def path_rate(path_m: np.ndarray, place: np.ndarray, step_s: float) -> np.ndarray:
    """(K, n) rate (m/s) of a (K, n) path between GNSS epochs ``step_s`` apart, by differences within each
    run of equal ``place`` (K,) (see the module docstring)."""
    epochs = path_m.shape[0]
    rate = np.zeros_like(path_m)
    if epochs < 2:
        return rate
    same = place[1:] == place[:-1]  # (K-1,): epoch k+1 shares epoch k's place
    forward = (path_m[1:] - path_m[:-1]) / step_s  # (K-1, n)
    has_next = np.append(same, False)
    has_previous = np.insert(same, 0, False)
    both = has_next & has_previous
    rate[both] = 0.5 * (forward[both[:-1]] + forward[both[1:]])
    only_next = has_next & ~has_previous
    rate[only_next] = forward[only_next[:-1]]
    only_previous = has_previous & ~has_next
    rate[only_previous] = forward[only_previous[1:]]
    return rate


def range_rate(
    line: np.ndarray,
    sat_velocity: np.ndarray,
    receiver_velocity: np.ndarray,
    receiver_drift_mps: np.ndarray,
    sat_clock_drift: np.ndarray,
    reflected_rate_mps: np.ndarray,
) -> np.ndarray:
    """(K, n) true range rate (m/s) before noise: ``line`` (K, n, 3) from the receiver to the rotated
    satellite, ``sat_velocity`` (K, n, 3) rotated the same way, ``receiver_velocity`` (K, 3) ECEF,
    ``receiver_drift_mps`` (K,), ``sat_clock_drift`` (n,) s/s, ``reflected_rate_mps`` (K, n)."""
    unit = line / np.linalg.norm(line, axis=-1, keepdims=True)
    relative = sat_velocity - receiver_velocity[:, None, :]
    geometric: np.ndarray = np.einsum("kni,kni->kn", unit, relative)
    rate: np.ndarray = (
        geometric
        + receiver_drift_mps[:, None]
        - SPEED_OF_LIGHT * sat_clock_drift[None, :]
        + reflected_rate_mps
    )
    return rate
