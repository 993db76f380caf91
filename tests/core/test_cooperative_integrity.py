"""core.cooperative_integrity: the range and fix sources' separation test on a linear problem.

A prior, a GNSS fix and three ranges, each drawn from its model: fault-free the tests fail at about
the false-alarm rate and the error stays within the protection level; a neighbour 20 m off along
the line of sight is pointed at; a filtered track's steps pass the step test and a 20 m jump fails it."""

from __future__ import annotations

import math

import numpy as np
from edgepos.core.cooperative_integrity import (
    RangeSource,
    cooperative_protection,
    fix_effect,
    separation_statistic,
    track_step_statistic,
)
from edgepos.core.integrity import IntegrityBudget

BUDGET = IntegrityBudget(1e-5, 1e-2, 1e-4, 5.0)
NEIGHBOURS = {"a": (30.0, 0.0), "b": (0.0, 25.0), "c": (-20.0, -20.0)}
PRIOR_STD, FIX_STD, RANGE_STD = 1.5, 3.0, 2.0


def solve(rng: np.random.Generator, offset: tuple[float, float] = (0.0, 0.0)):
    """One linearised epoch around the truth at the origin: the Kalman posterior and the protection."""
    truth = np.zeros(2)
    prior = truth + rng.standard_normal(2) * PRIOR_STD
    fix = truth + rng.standard_normal(2) * FIX_STD
    broadcast = {k: np.array(p) + (np.array(offset) if k == "a" else 0.0) for k, p in NEIGHBOURS.items()}
    measured = {
        k: float(np.linalg.norm(np.array(p)) + rng.standard_normal() * RANGE_STD)
        for k, p in NEIGHBOURS.items()
    }
    information = np.eye(2) / PRIOR_STD**2 + np.eye(2) / FIX_STD**2
    vector = prior / PRIOR_STD**2 + fix / FIX_STD**2
    for key, point in broadcast.items():
        u = -point / np.linalg.norm(point)  # from the neighbour to the linearisation point (origin)
        # range = |x - q| ~ |q| + u.x: the linear measurement u.x = range - |q|
        information += np.outer(u, u) / RANGE_STD**2
        vector += u * (measured[key] - np.linalg.norm(point)) / RANGE_STD**2
    cov = np.linalg.inv(information)
    x = cov @ vector
    sources = [
        RangeSource(k, (float(p[0]), float(p[1])), measured[k], RANGE_STD) for k, p in broadcast.items()
    ]
    own = fix_effect(
        float(x[0]), float(x[1]), (float(fix[0]), float(fix[1])), np.zeros(2), np.zeros((2, 2)), FIX_STD**2
    )
    return x, cooperative_protection(float(x[0]), float(x[1]), cov, own, sources, BUDGET)


def test_fault_free_tests_fail_at_about_the_false_alarm_rate_and_the_level_bounds_the_error():
    rng = np.random.default_rng(7)
    alarms, beyond = 0, 0
    for _ in range(3000):
        x, protection = solve(rng)
        alarms += protection.faulty is not None
        beyond += float(np.linalg.norm(x)) > protection.level
    # 4 tests sized to 1e-2 in all (2-dof threshold, 1-dof statistics for ranges: at most the budget)
    assert alarms <= 3000 * 1e-2 * 2
    assert beyond == 0


def test_a_neighbour_20_m_off_along_the_line_of_sight_is_pointed_at():
    rng = np.random.default_rng(8)
    for _ in range(50):
        _, protection = solve(rng, offset=(20.0, 0.0))
        assert protection.state == "alarm" and protection.faulty == 1  # 0 is the fix


def test_a_rank_one_separation_uses_its_one_direction():
    assert math.isclose(separation_statistic((4.0, 0.0, 0.0), 6.0, 0.0), 3.0)
    assert math.isclose(separation_statistic((4.0, 0.0, 1.0), 0.0, 2.0), 2.0)


def _filtered_track(rng: np.random.Generator, steps: int, dt: float = 0.2, fix_std: float = 3.5):
    """A constant-velocity Kalman filter on noisy position fixes of a vehicle driving at (15, 15) m/s with
    white acceleration 0.5 m/s^2: its estimates as track points (t, x, y, vx, vy, 4x4 cov of
    [x, y, vx, vy])."""
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt
    g = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]])
    q = g @ g.T * 0.5**2
    h = np.eye(2, 4)
    truth = np.array([0.0, 0.0, 15.0, 15.0])
    mean, cov = truth + rng.standard_normal(4) * [3.0, 3.0, 1.0, 1.0], np.diag([9.0, 9.0, 1.0, 1.0])
    points = []
    for k in range(steps):
        truth = f @ truth + g @ rng.standard_normal(2) * 0.5
        mean, cov = f @ mean, f @ cov @ f.T + q
        gain = cov @ h.T @ np.linalg.inv(h @ cov @ h.T + np.eye(2) * fix_std**2)
        mean = mean + gain @ (truth[:2] + rng.standard_normal(2) * fix_std - h @ mean)
        cov = (np.eye(4) - gain @ h) @ cov
        points.append((k * dt, *mean, tuple(map(tuple, cov))))
    return points


def test_a_filtered_track_passes_the_step_test_and_a_20_m_jump_in_any_direction_fails_it():
    rng = np.random.default_rng(4)
    threshold = math.sqrt(-2.0 * math.log(1e-4))  # chi-square, 2 dof, 1e-4
    statistics, jumps = [], []
    for run in range(20):
        points = _filtered_track(rng, 100)
        for k in range(1, len(points)):
            t0, x0, y0, vx, vy, p = points[k - 1]
            t1, x1, y1, _, _, c = points[k]
            statistics.append(track_step_statistic((t0, x0, y0, vx, vy, p), (t1, x1, y1, c), 0.5))
            angle = rng.uniform(-math.pi, math.pi)
            moved = (t1, x1 + 20.0 * math.cos(angle), y1 + 20.0 * math.sin(angle), c)
            jumps.append(track_step_statistic((t0, x0, y0, vx, vy, p), moved, 0.5))
    statistics, jumps = np.array(statistics), np.array(jumps)
    # Consecutive estimates' errors are correlated: the bound's statistic is smaller than chi-square's.
    assert np.mean(statistics > threshold) <= 1e-4 and np.mean(statistics**2) < 2.0
    assert np.all(jumps > threshold)
    assert track_step_statistic((1.0, 0.0, 0.0, 1.0, 0.0, np.eye(4)), (1.0, 50.0, 0.0, np.eye(4)), 1.0) == 0.0
