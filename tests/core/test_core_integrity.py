"""Solution separation and protection levels (core.integrity) against closed forms and Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.integrity import (
    ALARM,
    OK,
    UNAVAILABLE,
    IntegrityBudget,
    Protection,
    SourceEffect,
    new_protection,
    protect,
    radial_bound,
    separation_statistics,
)

BUDGET = IntegrityBudget(
    integrity_risk=1e-3, false_alarm_probability=1e-2, fault_probability=1e-2, alert_limit=10.0
)


def _linear_epoch(rng: np.random.Generator, bias: np.ndarray | None = None, faulty: int = 0):
    """A linear-Gaussian epoch: prior N(0, P0) on (x, y), three 2-D sources z_i = x + v_i (R_i), the exact
    posterior, and its sources' effects at the posterior."""
    prior = np.array([[0.5, 0.1], [0.1, 0.3]])
    noises = [np.diag([0.2, 0.4]), np.diag([0.3, 0.3]), np.array([[0.4, 0.05], [0.05, 0.2]])]
    truth = rng.multivariate_normal(np.zeros(2), prior)
    information = np.linalg.inv(prior)
    vector = np.zeros(2)  # prior mean 0
    measurements = []
    for index, noise in enumerate(noises):
        z = truth + rng.multivariate_normal(np.zeros(2), noise)
        if bias is not None and index == faulty:
            z = z + bias
        measurements.append(z)
        information = information + np.linalg.inv(noise)
        vector = vector + np.linalg.solve(noise, z)
    covariance = np.linalg.inv(information)
    estimate = covariance @ vector
    sources = []
    for z, noise in zip(measurements, noises):
        weight = np.linalg.inv(noise)
        sources.append(
            SourceEffect((weight[0, 0], weight[0, 1], weight[1, 1]), tuple(weight @ (z - estimate)))
        )
    return truth, estimate, covariance, sources


def test_radial_bound_matches_the_closed_forms_at_the_two_ends():
    # circular: P(|e| > R) = exp(-R^2 / 2 sigma^2)
    assert radial_bound((1.0, 0.0, 1.0), 1e-5) == pytest.approx(math.sqrt(-2 * math.log(1e-5)), rel=1e-6)
    # one-dimensional: the two-sided normal quantile (4.4172 sigma at 1e-5)
    assert radial_bound((4.0, 0.0, 0.0), 1e-5) == pytest.approx(2.0 * 4.41717, rel=1e-4)


def test_radial_bound_holds_by_monte_carlo_for_an_elongated_ellipse():
    rng = np.random.default_rng(1)
    covariance = np.array([[1.0, 0.6], [0.6, 0.5]])
    bound = radial_bound((1.0, 0.6, 0.5), 1e-2)
    errors = rng.multivariate_normal(np.zeros(2), covariance, size=200_000)
    exceed = np.mean(np.hypot(errors[:, 0], errors[:, 1]) > bound)
    assert 0.008 < exceed <= 0.0105  # tabulated from above: at most the risk, not far below it


def test_separation_statistics_are_chi_square_with_two_degrees_of_freedom_when_fault_free():
    rng = np.random.default_rng(2)
    squares = np.array(
        [
            np.square(separation_statistics(covariance.tolist(), sources))
            for _, _, covariance, sources in (_linear_epoch(rng) for _ in range(4000))
        ]
    )
    # each source's q: mean 2, and P(q > 5.991) = 5 %
    assert squares.mean(axis=0) == pytest.approx([2.0, 2.0, 2.0], abs=0.15)
    assert np.mean(squares > 5.991, axis=0) == pytest.approx([0.05, 0.05, 0.05], abs=0.012)


def test_fault_free_protection_level_bounds_the_error_at_the_risk():
    rng = np.random.default_rng(3)
    exceed = 0
    runs = 4000
    for _ in range(runs):
        truth, estimate, covariance, sources = _linear_epoch(rng)
        result = protect(covariance.tolist(), sources, BUDGET)
        if result.state == OK and np.hypot(*(estimate - truth)) > result.level:
            exceed += 1
    assert exceed / runs <= BUDGET.integrity_risk + 3 * math.sqrt(BUDGET.integrity_risk / runs)


def test_a_large_fault_is_detected_and_pointed_at():
    rng = np.random.default_rng(4)
    for faulty in range(3):
        _, _, covariance, sources = _linear_epoch(rng, bias=np.array([6.0, -4.0]), faulty=faulty)
        result = protect(covariance.tolist(), sources, BUDGET)
        assert result.state == ALARM and result.faulty == faulty


def test_undetected_faults_stay_within_the_protection_level():
    """A bias near the detection threshold, the hardest case: undetected epochs keep the error within PL."""
    rng = np.random.default_rng(5)
    misleading = 0
    for _ in range(3000):
        truth, estimate, covariance, sources = _linear_epoch(rng, bias=np.array([1.2, 0.0]), faulty=0)
        result = protect(covariance.tolist(), sources, BUDGET)
        if result.faulty is None and result.state == OK and np.hypot(*(estimate - truth)) > result.level:
            misleading += 1
    assert misleading <= 2  # a bound at 1e-3 / 2 / 3 per hypothesis: a handful at most in 3000


def test_the_protection_level_above_the_alert_limit_is_an_alarm():
    rng = np.random.default_rng(6)
    _, _, covariance, sources = _linear_epoch(rng)
    result = protect(covariance.tolist(), sources, IntegrityBudget(1e-3, 1e-9, 1e-2, 0.01))
    assert result.state == ALARM and result.faulty is None and result.level > 0.01


def test_a_singular_covariance_is_unavailable_not_a_number():
    result = protect([[0.0, 0.0], [0.0, 0.0]], [], BUDGET)
    assert result.state == UNAVAILABLE and result.level is None


def test_the_trusted_constructor_gives_the_same_protection() -> None:
    """``new_protection`` (the RSU monitor's per-epoch constructor) builds what ``Protection(level, state)``
    does: equal both ways, hashed, pickled and printed alike, still frozen and ``dataclasses.replace``-able."""
    import dataclasses
    import pickle

    for level, state in ((0.8, OK), (None, UNAVAILABLE), (2.5, ALARM)):
        built, trusted = Protection(level, state), new_protection(level, state)
        assert trusted == built and built == trusted and hash(trusted) == hash(built)
        assert repr(trusted) == repr(built) and pickle.loads(pickle.dumps(trusted)) == built
        assert trusted.faulty is None and trusted.statistic is None and trusted.threshold is None
        assert dataclasses.replace(trusted, state=ALARM) == Protection(level, ALARM)
        with pytest.raises(dataclasses.FrozenInstanceError):
            trusted.level = 1.0  # type: ignore[misc]
    assert new_protection(0.8, OK) != Protection(0.8, OK, faulty=1)
