"""The V2X federated paper's scenario (Wang et al. 2019, sec. 3), deterministic from a seed.

A target vehicle drives east at 10 m/s for 300 steps of 0.2 s; its acceleration on each axis is a
first-order Markov (Singer) process with time constant 1/0.1 s and standard deviation 0.3 m/s^2.
Four assisting vehicles drive east at the same speed, 30 m apart; each knows its own position from
GNSS fixes with a 1 m 1-sigma error per axis (they have the good sky view of the paper's Fig. 1),
which its own session filters and publishes as the track the target's V2X sub-filter reads. Sensors: GNSS fixes (1-sigma sqrt(15) m
per axis clean, sqrt(50) m under multipath: see docs/federated.md for that reading), gyro yaw rate
(0.005 rad/s), odometer distance per step (0.1 m), V2V ranges to every assisting vehicle (3 m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edgepos.core.motion.base import van_loan
from edgepos.core.motion.singer import singer_drift
from edgepos.core.observations import (
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    V2vRangeObservation,
)

STEP = 0.2
STEPS = 300
SPEED = 10.0
ACCEL_ALPHA = 0.1
ACCEL_STD = 0.3
GPS_STD = {"clean": math.sqrt(15.0), "multipath": math.sqrt(50.0)}
GYRO_STD = 0.005
ODOMETER_STD = 0.1
RANGE_STD = 3.0
NEIGHBOUR_STD = 1.0
#: Assisting vehicles' offsets (along-track, cross-track) from the target, m: 30 m apart in the
#: two lanes either side of the target's (3.5 m lanes), so that ranges fix both axes.
NEIGHBOUR_OFFSETS = ((-45.0, 3.5), (-15.0, -3.5), (15.0, 3.5), (45.0, -3.5))
SCENARIOS = tuple(GPS_STD)

#: Pipeline options for the paper's model (sec. 3): white GNSS errors, the assisting vehicles' positions as independent of the target's.
PAPER_OPTIONS = {"gnss_bias_std": 0.0, "neighbour_fusion": "independent"}


@dataclass(frozen=True)
class FederatedRun:
    """One run: the target's truth (steps, 6) [x, vx, ax, y, vy, ay], its observations per step (all
    kinds; each method is fed a subset), and each assisting vehicle's own GNSS fix per step."""

    times: np.ndarray
    truth: np.ndarray
    observations: list[list[Observation]]
    neighbour_ids: tuple[str, ...]
    neighbour_fixes: list[dict[str, GnssFixObservation]]
    neighbour_truth: np.ndarray  # (steps, neighbours, 2)


def truth_trajectory(rng: np.random.Generator, steps: int = STEPS) -> np.ndarray:
    """Target states (steps, 6): start at the origin heading east at SPEED, Singer acceleration."""
    transition_axis, noise_axis = van_loan(
        singer_drift(ACCEL_ALPHA), np.diag([0.0, 0.0, 2.0 * ACCEL_ALPHA * ACCEL_STD**2]), STEP
    )
    factor = np.linalg.cholesky(noise_axis + 1e-15 * np.eye(3))
    state = np.zeros((2, 3))
    state[0, 1] = SPEED
    rows = []
    for _ in range(steps):
        rows.append(state.reshape(-1).copy())
        state = state @ transition_axis.T + (factor @ rng.standard_normal((3, 2))).T
    return np.array(rows)


def make_run(seed: int, run: int, scenario: str, steps: int = STEPS) -> FederatedRun:
    """Run ``run`` of ``scenario`` ("clean" or "multipath") from numpy default_rng([seed, run]).

    Both scenarios of one (seed, run) share the trajectory and every noise draw except the GNSS
    error's scale, so their difference is the multipath alone."""
    rng = np.random.default_rng([seed, run])
    truth = truth_trajectory(rng, steps)
    times = np.arange(steps) * STEP
    gps_noise = rng.standard_normal((steps, 2)) * GPS_STD[scenario]
    gyro_noise = rng.standard_normal(steps) * GYRO_STD
    odo_noise = rng.standard_normal(steps) * ODOMETER_STD
    range_noise = rng.standard_normal((steps, len(NEIGHBOUR_OFFSETS))) * RANGE_STD
    publish_noise = rng.standard_normal((steps, len(NEIGHBOUR_OFFSETS), 2)) * NEIGHBOUR_STD
    ids = tuple(f"assist-{k + 1}" for k in range(len(NEIGHBOUR_OFFSETS)))
    offsets = np.array(NEIGHBOUR_OFFSETS)
    neighbour_truth = np.array([[SPEED * t, 0.0] + offsets for t in times])
    observations: list[list[Observation]] = []
    neighbour_fixes: list[dict[str, GnssFixObservation]] = []
    for k, t in enumerate(times):
        x, vx, ax, y, vy, ay = truth[k]
        speed_sq = vx * vx + vy * vy
        yaw_rate = (vx * ay - ax * vy) / speed_sq
        epoch: list[Observation] = [
            GnssFixObservation(
                float(t), float(x + gps_noise[k, 0]), float(y + gps_noise[k, 1]), GPS_STD[scenario]
            ),
            GyroObservation(float(t), float(yaw_rate + gyro_noise[k])),
            OdometerObservation(
                float(t), distance=float(max(STEP * math.sqrt(speed_sq) + odo_noise[k], 0.0))
            ),
        ]
        step_fixes = {}
        for n, vid in enumerate(ids):
            known = neighbour_truth[k, n] + publish_noise[k, n]
            step_fixes[vid] = GnssFixObservation(float(t), float(known[0]), float(known[1]), NEIGHBOUR_STD)
            distance = float(np.hypot(*(neighbour_truth[k, n] - [x, y])))
            epoch.append(V2vRangeObservation(float(t), vid, range=max(distance + range_noise[k, n], 0.0)))
        observations.append(epoch)
        neighbour_fixes.append(step_fixes)
    return FederatedRun(times, truth, observations, ids, neighbour_fixes, neighbour_truth)
