"""A cooperative scene nobody tuned to: four vehicles on an S-curved road whose GNSS fix errors are
time-correlated and partly common to all of them, as on a real street (issue 21, item 0).

The road's heading is psi(s) = ROAD_SWING sin(2 pi s / ROAD_WAVELENGTH) along its arc length s; the
vehicles follow one another on it, SPACING apart, each at its own speed varying around CRUISE. Every
STEP each vehicle measures its gyro yaw rate, its odometer distance over the step and the time of
arrival of a V2V signal from every other vehicle; every ``fix_interval`` it gets a GNSS fix whose
error per axis is

    common Gauss-Markov (shared by the four) + own Gauss-Markov + white,

each Gauss-Markov process first-order with its time constant and stationary standard deviation
(:class:`ErrorModel`; the defaults' sizes are those measured on the real recording, docs/v2v.md).
A fix carries its total 1-sigma per axis, as a receiver reports it. Deterministic from a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edgepos.core.observations import (
    SPEED_OF_LIGHT,
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    V2vRangeObservation,
)

STEP = 0.2
STEPS = 300
VEHICLES = 4
VEHICLE_IDS = tuple(f"car-{i + 1}" for i in range(VEHICLES))
ROAD_SWING = 0.7
"""rad: the road's heading swings +-40 degrees either side of east."""
ROAD_WAVELENGTH = 400.0
"""m: one S (a left and a right bend) every 400 m."""
SPACING = 25.0
CRUISE = 12.0
GYRO_STD = 0.005
ODOMETER_STD = 0.1
RANGE_STD = 2.0
_ROAD_RESOLUTION = 0.25


@dataclass(frozen=True)
class ErrorModel:
    """GNSS fix error per axis (m): common and per-vehicle first-order Gauss-Markov processes (time
    constant s, stationary 1-sigma m) plus white noise; fixes every ``fix_interval`` s."""

    common_tau: float = 60.0
    common_std: float = 2.0
    vehicle_tau: float = 20.0
    vehicle_std: float = 1.5
    white_std: float = 1.0
    fix_interval: float = 1.0

    @property
    def total_std(self) -> float:
        return math.sqrt(self.common_std**2 + self.vehicle_std**2 + self.white_std**2)


@dataclass(frozen=True)
class CorrelatedRun:
    """One run: times (steps,), true positions and velocities (vehicles, steps, 2), the fix errors
    (vehicles, steps, 2; NaN where no fix) and each vehicle's observations per step."""

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    fix_errors: np.ndarray
    observations: list[list[list[Observation]]]


def gauss_markov_series(
    rng: np.random.Generator, tau: float, std: float, times: np.ndarray, shape: tuple[int, ...]
) -> np.ndarray:
    """Samples (len(times), *shape) of a stationary first-order Gauss-Markov process, started from its
    stationary distribution and stepped exactly: x' = phi x + sqrt(1 - phi^2) std w, phi = exp(-dt/tau)."""
    out = np.zeros((len(times), *shape))
    value = rng.standard_normal(shape) * std
    for k, t in enumerate(times):
        if k:
            phi = math.exp(-(t - times[k - 1]) / tau)
            value = phi * value + math.sqrt(1.0 - phi * phi) * std * rng.standard_normal(shape)
        out[k] = value
    return out


def _road(length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arc lengths, points (n, 2) and headings of the road's centreline from s = 0 to ``length``."""
    s = np.arange(0.0, length + _ROAD_RESOLUTION, _ROAD_RESOLUTION)
    heading = ROAD_SWING * np.sin(2.0 * math.pi * s / ROAD_WAVELENGTH)
    mid = 0.5 * (heading[1:] + heading[:-1])
    steps = _ROAD_RESOLUTION * np.stack([np.cos(mid), np.sin(mid)], axis=1)
    points = np.vstack([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
    return s, points, heading


def make_run(seed: int, errors: ErrorModel = ErrorModel(), steps: int = STEPS) -> CorrelatedRun:
    """The run of ``seed`` (numpy default_rng([seed, 21])): trajectories, sensor readings and fixes."""
    rng = np.random.default_rng([seed, 21])
    times = np.arange(steps) * STEP
    phases = rng.uniform(0.0, 2.0 * math.pi, VEHICLES)
    # Speed CRUISE + 1.5 sin(2 pi t / 20 + phase): arc length in closed form.
    arc = np.array(
        [
            (VEHICLES - 1 - i) * SPACING
            + CRUISE * times
            - 1.5
            * 20.0
            / (2.0 * math.pi)
            * (np.cos(2.0 * math.pi * times / 20.0 + phases[i]) - math.cos(phases[i]))
            for i in range(VEHICLES)
        ]
    )
    speed = CRUISE + 1.5 * np.sin(2.0 * math.pi * times[None, :] / 20.0 + phases[:, None])
    s, points, heading = _road(float(arc.max()) + 10.0)
    positions = np.stack([np.interp(arc, s, points[:, 0]), np.interp(arc, s, points[:, 1])], axis=-1)
    psi = np.interp(arc, s, heading)
    velocity = speed[..., None] * np.stack([np.cos(psi), np.sin(psi)], axis=-1)
    yaw_rate = (
        ROAD_SWING * 2.0 * math.pi / ROAD_WAVELENGTH * np.cos(2.0 * math.pi * arc / ROAD_WAVELENGTH) * speed
    )
    common = gauss_markov_series(rng, errors.common_tau, errors.common_std, times, (2,))
    own = gauss_markov_series(rng, errors.vehicle_tau, errors.vehicle_std, times, (VEHICLES, 2))
    white = rng.standard_normal((steps, VEHICLES, 2)) * errors.white_std
    fix_error = np.transpose(common[:, None, :] + own + white, (1, 0, 2))
    every = max(1, round(errors.fix_interval / STEP))
    has_fix = (np.arange(steps) % every) == 0
    fix_error[:, ~has_fix] = np.nan
    gyro_noise = rng.standard_normal((VEHICLES, steps)) * GYRO_STD
    odometer_noise = rng.standard_normal((VEHICLES, steps)) * ODOMETER_STD
    range_noise = rng.standard_normal((VEHICLES, steps, VEHICLES)) * RANGE_STD
    observations: list[list[list[Observation]]] = []
    for i in range(VEHICLES):
        per_step = []
        for k in range(steps):
            t = float(times[k])
            travelled = float(arc[i, k] - arc[i, k - 1]) if k else 0.0
            epoch: list[Observation] = []
            if has_fix[k]:
                fix = positions[i, k] + fix_error[i, k]
                epoch.append(GnssFixObservation(t, float(fix[0]), float(fix[1]), errors.total_std))
            epoch.append(GyroObservation(t, float(yaw_rate[i, k] + gyro_noise[i, k])))
            epoch.append(OdometerObservation(t, distance=max(travelled + float(odometer_noise[i, k]), 0.0)))
            for j in range(VEHICLES):
                if j != i:
                    distance = float(np.linalg.norm(positions[j, k] - positions[i, k]))
                    toa = max(distance + float(range_noise[i, k, j]), 0.0) / SPEED_OF_LIGHT
                    epoch.append(V2vRangeObservation(t, VEHICLE_IDS[j], toa=toa))
            per_step.append(epoch)
        observations.append(per_step)
    return CorrelatedRun(times, positions, velocity, fix_error, observations)
