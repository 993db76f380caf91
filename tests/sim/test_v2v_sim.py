"""The V2V paper's simulated scenes: the true path agrees with what the simulated sensors say of it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.observations import GyroObservation, OdometerObservation
from edgepos.sim import v2v


def _yaw_rates(run: v2v.V2vRun, vehicle: int) -> np.ndarray:
    return np.array(
        [o.yaw_rate for e in run.observations[vehicle] for o in e if isinstance(o, GyroObservation)]
    )


def _distances(run: v2v.V2vRun, vehicle: int) -> np.ndarray:
    epochs = run.observations[vehicle]
    return np.array([o.distance for e in epochs for o in e if isinstance(o, OdometerObservation)])


def test_the_ring_follows_the_arcs_its_yaw_rates_and_speeds_describe() -> None:
    """Dead reckoning with the true yaw rate held over each step (exact arcs) and the true speed lands on
    every true position: the path turns during the step the gyro reports the turn for. Moving along the
    step's first heading and turning at its end (Euler) would be metres off after a quarter turn."""
    velocity = v2v.velocities("ring")
    positions, headings, travelled = v2v.track(velocity)
    yaw_rates = np.diff(headings, axis=1) / v2v.STEP
    for i in range(v2v.VEHICLES):
        x, y = positions[i, 0]
        heading = headings[i, 0]
        speed = float(np.hypot(*velocity[i, 0]))
        for k in range(1, velocity.shape[1]):
            turn = yaw_rates[i, k - 1] * v2v.STEP
            arc = speed * v2v.STEP
            assert travelled[i, k] == pytest.approx(arc, rel=1e-12)
            chord = arc if turn == 0.0 else arc * math.sin(turn / 2.0) / (turn / 2.0)
            x += chord * math.cos(heading + turn / 2.0)
            y += chord * math.sin(heading + turn / 2.0)
            heading += turn
            assert (x, y) == pytest.approx(tuple(positions[i, k]), abs=1e-9)
        euler = positions[i, 0] + v2v.STEP * velocity[i, :-1].sum(axis=0)
        assert float(np.hypot(*(euler - positions[i, -1]))) > 4.0  # what the first form of the scene did


def test_the_sensors_read_the_path() -> None:
    """Noise-free parts of the readings: the gyro's yaw rate is the heading change over the step, the
    odometer's distance the arc travelled (their noise is 0.005 rad/s and 0.1 m)."""
    run = v2v.make_run(0, 0, "ring")
    _, headings, travelled = v2v.track(run.velocities)
    for i in range(v2v.VEHICLES):
        gyro, odometer = _yaw_rates(run, i), _distances(run, i)
        truth_rate = np.diff(headings[i]) / v2v.STEP
        assert np.std(gyro[1:] - truth_rate) < 3 * v2v.GYRO_STD
        assert abs(np.mean(gyro[1:] - truth_rate)) < 3 * v2v.GYRO_STD / math.sqrt(len(truth_rate))
        assert np.std(odometer[1:] - travelled[i, 1:]) < 3 * v2v.ODOMETER_STD


def test_the_straight_scene_is_the_paper_s_constant_velocity() -> None:
    run = v2v.make_run(0, 0, "straight")
    steps = np.diff(run.positions, axis=1)
    assert np.allclose(steps, v2v.STEP * 15.0)
