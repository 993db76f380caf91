"""gnss/raim.py on synthetic geometry: the leave-one-out downdate equals solving again without the
satellite, a biased satellite fails its test and no other, a constellation fault points at the constellation,
too few satellites are unavailable, and the protection level bounds the fault-free and the faulty error."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.integrity import ALARM, OK, UNAVAILABLE, radial_bound
from edgepos.gnss.raim import RaimBudget, _solve, _statistic, protection, separations

BUDGET = RaimBudget(1e-5, 1e-4, 1e-4, 1e-4, 1000.0, 1.0)


def _geometry(count: int, systems: str, seed: int = 0) -> tuple[np.ndarray, list[str]]:
    """Unit lines of sight above 10 deg elevation as (north, east, up) Jacobian rows plus clock columns."""
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(0, 2 * np.pi, count)
    elevation = rng.uniform(np.radians(10), np.radians(85), count)
    los = np.column_stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
    )
    names = [systems[k % len(systems)] for k in range(count)]
    groups = sorted(set(names))
    h = np.zeros((count, 3 + len(groups)))
    h[:, :3] = -los
    for k, name in enumerate(names):
        h[k, 3 + groups.index(name)] = 1.0
    return h, names


def _split_clock(h: np.ndarray, names: list[str]) -> np.ndarray:
    """The first constellation's rows on two clock columns: its hypothesis leaves two columns, the others
    one, so the constellations' normal matrices differ in size."""
    first = [k for k, n in enumerate(names) if n == names[0]]
    extra = np.zeros((len(names), 1))
    extra[first[::2], 0], h = 1.0, h.copy()
    h[first[::2], 3] = 0.0
    return np.hstack([h, extra])


@pytest.mark.parametrize("numba", ["1", "0"])
@pytest.mark.parametrize(
    ("count", "systems", "lone", "split"),
    [(12, "GC", False, False), (14, "GCE", False, False), (13, "GCE", True, False), (14, "GCE", False, True)],
)
def test_the_downdate_equals_solving_without_the_satellite(
    count, systems, lone, split, numba, monkeypatch
) -> None:
    """Every hypothesis (the batched one-satellite downdates, the constellations' solves in one inversion, a
    constellation's only satellite) against solving again without its rows, one at a time; by the compiled
    kernel (core/measurements/gnss_raim_kernel.py) and by the numpy form (EDGEPOS_NUMBA=0). A
    constellation's only satellite fixes only its own clock: its separation and covariance are zero but for
    rounding, and its statistic that rounding's ratio (1e-7 sigma here), hence the absolute 1e-6."""
    monkeypatch.setenv("EDGEPOS_NUMBA", numba)
    h, names = _geometry(count, systems)
    if lone:  # the last satellite alone in its constellation "J"
        names[-1] = "J"
        groups = sorted(set(names))
        h = np.zeros((count, 3 + len(groups)))
        h[:, :3] = _geometry(count, systems)[0][:, :3]
        for k, name in enumerate(names):
            h[k, 3 + groups.index(name)] = 1.0
    if split:
        h = _split_clock(h, names)
    rng = np.random.default_rng(1)
    z, std = rng.normal(0, 2, count), rng.uniform(1, 3, count)
    prior = np.diag([4.0, 4.0, 9.0])
    result = separations(h, names, z, std, prior, BUDGET)
    assert result.available
    assert len(result.hypotheses) == count + len(set(names))
    w = 1 / std**2
    full = _solve(h, w, z, np.linalg.inv(prior), np.ones(count, bool))
    assert full is not None
    for rows, separation, covariance, statistic, _ in result.hypotheses:
        keep = np.ones(count, bool)
        keep[list(rows)] = False
        subset = _solve(h, w, z, np.linalg.inv(prior), keep)
        assert subset is not None
        assert np.allclose(separation, subset[0] - full[0], atol=1e-9)
        assert np.allclose(covariance, subset[1] - full[1], atol=1e-9)
        expected = _statistic(subset[0] - full[0], 0.5 * ((subset[1] - full[1]) + (subset[1] - full[1]).T))
        assert statistic == pytest.approx(expected, rel=1e-6, abs=1e-6)


def test_a_biased_satellite_fails_its_test_and_only_it() -> None:
    h, names = _geometry(10, "GCE")
    rng = np.random.default_rng(2)
    std = np.full(10, 1.0)
    z = rng.normal(0, 1, 10)
    clean = separations(h, names, z, std, np.eye(3) * 25.0, BUDGET)
    assert clean.available and clean.worst() is None
    z[4] += 40.0
    faulty = separations(h, names, z, std, np.eye(3) * 25.0, BUDGET)
    worst = faulty.worst()
    assert worst is not None and faulty.hypotheses[worst[0]][0] == (4,)
    assert protection(faulty, np.eye(2), BUDGET).state == ALARM
    # found once per separations (the exclusion and the protection level both ask), the same each time
    assert faulty.worst() is worst and faulty.worst(size=1) == worst


def test_a_constellation_fault_points_at_the_constellation() -> None:
    h, names = _geometry(15, "GCE")
    z = np.random.default_rng(3).normal(0, 1, 15)
    # a common error of the BeiDou ranges that is not a clock offset: it grows with the line of sight's east
    z += np.array([30.0 * max(row[1], 0.0) + 10.0 if n == "C" else 0.0 for row, n in zip(h, names)])
    result = separations(h, names, z, np.ones(15), np.eye(3) * 1e4, BUDGET)
    worst = result.worst(size=2)  # the constellations' tests; exclusion tries the worst satellite first
    assert worst is not None
    assert {names[r] for r in result.hypotheses[worst[0]][0]} == {"C"}
    assert len(result.hypotheses[worst[0]][0]) == names.count("C")


def _level_one_by_one(result, fix_cov: np.ndarray, budget: RaimBudget) -> float:
    """The protection level as raim.protection computed it before its hypotheses were taken as arrays."""
    covariance = budget.inflation * fix_cov
    covariance = 0.5 * (covariance + covariance.T)
    fault_free = 0.5 * budget.integrity_risk
    level = radial_bound((covariance[0, 0], covariance[0, 1], covariance[1, 1]), fault_free)
    per_hypothesis = fault_free / max(len(result.hypotheses), 1)
    for _, _, s, _, probability in result.hypotheses:
        a, b, d = float(s[0, 0]), float(s[0, 1]), float(s[1, 1])
        largest = 0.5 * (a + d) + math.hypot(0.5 * (a - d), b)
        m = covariance + s
        bound = result.threshold * math.sqrt(max(largest, 0.0)) + radial_bound(
            (float(m[0, 0]), float(m[0, 1]), float(m[1, 1])), per_hypothesis / probability
        )
        level = max(level, bound)
    return level


@pytest.mark.parametrize("seed", range(6))
def test_the_protection_level_is_the_one_by_one_maximum(seed: int) -> None:
    """Satellite and constellation hypotheses with different prior fault probabilities, one of them 1e-9 (a
    per-hypothesis probability of 1 or more needs no bound): the arrays give the loop's level exactly."""
    h, names = _geometry(8 + 3 * seed, "GCE", seed=seed)
    rng = np.random.default_rng(seed)
    budget = RaimBudget(1e-5, 1e-4, 10.0 ** -rng.uniform(2, 6), 1e-9 if seed == 5 else 1e-4, 1000.0, 3.0)
    result = separations(
        h, names, rng.normal(0, 2, len(names)), rng.uniform(1, 3, len(names)), np.eye(3) * 9.0, budget
    )
    fix_cov = np.array([[2.0, 0.3 * seed - 0.5], [0.3 * seed - 0.5, 1.5 + seed]])
    assert protection(result, fix_cov, budget).level == _level_one_by_one(result, fix_cov, budget)


def test_too_few_satellites_are_unavailable() -> None:
    h, names = _geometry(5, "GC")
    result = separations(h, names, np.zeros(5), np.ones(5), np.eye(3), BUDGET)
    assert not result.available
    assert protection(result, np.eye(2), BUDGET).state == UNAVAILABLE


def test_the_protection_level_bounds_the_error_of_simulated_epochs() -> None:
    """Fault-free epochs and epochs with one satellite biased by up to 30 sigma: the error of the
    all-in-view solution exceeds the protection level only in alarm (the solution is the filter here)."""
    h, names = _geometry(9, "GC", seed=4)
    rng = np.random.default_rng(5)
    prior = np.eye(3) * 100.0
    w = np.ones(9)
    misleading = ok = 0
    for trial in range(2000):
        z = rng.normal(0, 1, 9)
        truth_error = rng.multivariate_normal(np.zeros(3), prior)
        z += h[:, :3] @ (-truth_error)  # the prediction is off by the prior's error
        if trial % 2:
            z[rng.integers(9)] += rng.uniform(0, 30)
        result = separations(h, names, z, np.ones(9), prior, BUDGET)
        solved = _solve(h, w, z, np.linalg.inv(prior), np.ones(9, bool))
        assert solved is not None
        estimate, cov = solved
        guard = protection(result, cov, BUDGET)
        # the solution d estimates the correction to the prediction: its error is d + truth_error
        error = float(np.hypot(*(estimate + truth_error[[1, 0]])))
        ok += guard.state == OK and trial % 2 == 0
        if guard.state == OK and guard.level is not None and error > guard.level:
            misleading += 1
    assert misleading == 0
    assert ok >= 990  # not by putting everything in alarm: the fault-free epochs pass (P_FA 1e-4)
