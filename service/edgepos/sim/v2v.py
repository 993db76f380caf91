"""The V2V cooperative-positioning paper's scenarios (Qiao & Qu 2021, sec. 4), deterministic from a seed.

Four vehicles, 100 steps of 0.2 s. ``straight``: all drive at vx = vy = 15 m/s (sec. 4.1).
``ring``: vehicle i drives at (15 + i) sqrt(2) m/s through the four phases of eqs. 27-30: a
quarter turn, straight, a quarter turn, straight (see docs/v2v.md for the turn rate, printed as
"36 rad/s"). Each vehicle measures, every step: a GNSS fix (1-sigma 5/sqrt(2) m per axis), its
gyro yaw rate (0.005 rad/s), its odometer distance over the step (0.1 m) and the time of arrival
of a V2V signal from each other vehicle (1-sigma 2 m / c). Where the paper does not give the
starting positions, the vehicles start at the corners of a 20 m square.
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
STEPS = 100
VEHICLES = 4
GPS_STD = 5.0 / math.sqrt(2.0)
GYRO_STD = 0.005
ODOMETER_STD = 0.1
RANGE_STD = 2.0
TURN_RATE = math.pi / 10.0
"""rad/s: eqs. 27-30 join continuously only if 25 steps turn through a quarter circle (25 phi T = pi/2)."""
STARTS = ((0.0, 0.0), (20.0, 0.0), (0.0, 20.0), (20.0, 20.0))
SCENARIOS = ("straight", "ring")
VEHICLE_IDS = tuple(f"veh-{i + 1}" for i in range(VEHICLES))

#: Pipeline options for the paper's model (sec. 4): white GNSS errors, neighbours' estimates as independent information.
PAPER_OPTIONS = {"gnss_bias_std": 0.0, "neighbour_fusion": "independent"}


@dataclass(frozen=True)
class V2vRun:
    """One run: times (steps,), every vehicle's true positions (vehicles, steps, 2) and velocities,
    and its observations per step (vehicles x steps lists)."""

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    observations: list[list[list[Observation]]]


def velocities(scenario: str, steps: int = STEPS) -> np.ndarray:
    """True velocities (vehicles, steps, 2) in m/s; step k (0-based) is the paper's k + 1."""
    out = np.zeros((VEHICLES, steps, 2))
    for i in range(VEHICLES):
        if scenario == "straight":
            out[i, :] = (15.0, 15.0)
            continue
        speed = (15.0 + (i + 1)) * math.sqrt(2.0)
        for index in range(steps):
            k = index + 1
            if k <= 25:
                angle = k * TURN_RATE * STEP
            elif k <= 50:
                angle = 25 * TURN_RATE * STEP
            elif k <= 75:
                angle = (k - 25) * TURN_RATE * STEP
            else:
                angle = 50 * TURN_RATE * STEP
            out[i, index] = (-speed * math.sin(angle), speed * math.cos(angle))
        # eq. 28 carries -cos for phase 2: with 25 phi T = pi/2 both signs give vy = 0
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {SCENARIOS}")
    return out


def track(velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True positions (vehicles, steps, 2), headings (vehicles, steps; rad, unwrapped) and distances
    travelled over each step (vehicles, steps; 0 at the first) of vehicles at ``velocity``.

    Between steps a vehicle keeps its speed and turns at a constant rate from one step's heading to the
    next one's, as a road vehicle does and as the gyro's yaw rate (the heading change over the step)
    says: the step's chord points at the mean of the two headings and is sinc(turn / 2) of the arc. The
    paper's state carries the acceleration (a = v', sec. 4.2), so its positions follow the turn to
    second order; moving along the step's first heading and turning at its end (Euler) would put each
    turning step 0.16 m (vehicle 3) off the arc the gyro describes, about 4 m over a quarter turn."""
    steps = velocity.shape[1]
    headings = np.unwrap(np.arctan2(velocity[..., 1], velocity[..., 0]), axis=1)
    positions = np.zeros_like(velocity)
    positions[:, 0] = STARTS
    travelled = np.zeros(velocity.shape[:2])
    for k in range(1, steps):
        straight = STEP * velocity[:, k - 1]
        turn = headings[:, k] - headings[:, k - 1]
        arc = STEP * np.hypot(velocity[:, k - 1, 0], velocity[:, k - 1, 1])
        half = turn / 2.0
        chord = arc * np.sinc(half / np.pi)  # numpy's sinc is sin(pi x) / (pi x)
        direction = headings[:, k - 1] + half
        curved = chord[:, None] * np.stack([np.cos(direction), np.sin(direction)], axis=1)
        turning = (turn != 0.0)[:, None]
        positions[:, k] = positions[:, k - 1] + np.where(turning, curved, straight)
        moved = np.linalg.norm(positions[:, k] - positions[:, k - 1], axis=1)
        travelled[:, k] = np.where(turning[:, 0], arc, moved)
    return positions, headings, travelled


def make_run(seed: int, run: int, scenario: str, steps: int = STEPS) -> V2vRun:
    """Run ``run`` of ``scenario`` from numpy default_rng([seed, run, scenario index])."""
    rng = np.random.default_rng([seed, run, SCENARIOS.index(scenario) if scenario in SCENARIOS else 99])
    velocity = velocities(scenario, steps)
    positions, headings, travelled = track(velocity)
    yaw_rates = np.zeros((VEHICLES, steps))
    yaw_rates[:, 1:] = np.diff(headings, axis=1) / STEP
    times = np.arange(steps) * STEP
    gps_noise = rng.standard_normal((VEHICLES, steps, 2)) * GPS_STD
    gyro_noise = rng.standard_normal((VEHICLES, steps)) * GYRO_STD
    odometer_noise = rng.standard_normal((VEHICLES, steps)) * ODOMETER_STD
    range_noise = rng.standard_normal((VEHICLES, steps, VEHICLES)) * RANGE_STD
    observations: list[list[list[Observation]]] = []
    for i in range(VEHICLES):
        per_step = []
        for k in range(steps):
            t = float(times[k])
            fix = positions[i, k] + gps_noise[i, k]
            epoch: list[Observation] = [
                GnssFixObservation(t, float(fix[0]), float(fix[1])),
                GyroObservation(t, float(yaw_rates[i, k] + gyro_noise[i, k])),
                OdometerObservation(
                    t, distance=max(float(travelled[i, k]) + float(odometer_noise[i, k]), 0.0)
                ),
            ]
            for j in range(VEHICLES):
                if j == i:
                    continue
                distance = float(np.linalg.norm(positions[j, k] - positions[i, k]))
                toa = max(distance + float(range_noise[i, k, j]), 0.0) / SPEED_OF_LIGHT
                epoch.append(V2vRangeObservation(t, VEHICLE_IDS[j], toa=toa))
            per_step.append(epoch)
        observations.append(per_step)
    return V2vRun(times, positions, velocity, observations)
