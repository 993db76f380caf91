"""Time-correlated pseudorange errors (gnss.error_correlation): the variance of an average of AR(1) errors
against its direct sum and a simulation, the consider factor against its closed cases, and a Kalman filter
fed correlated errors whose white covariance is too small and whose covariance times the factor is not."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.gnss.error_correlation import (
    FITTED_CORRELATION,
    ErrorCorrelation,
    averaged_variance,
    correlation,
    honest_factor,
    long_run_factor,
    mean_variance,
)


def memory_factors(count: np.ndarray, memory: float, model: ErrorCorrelation, dt: float) -> np.ndarray:
    """The variance of each row's errors over ``memory`` epochs against the 1/memory of white errors."""
    averaged, own = averaged_variance(count, memory, model, dt)
    np.testing.assert_allclose(own, model.smoothed_variance(np.maximum(count, 1.0), dt))
    return averaged / own


def _direct(n: int, rho: float) -> float:
    return (1.0 + 2.0 * sum((1.0 - k / n) * rho**k for k in range(1, n))) / n


@pytest.mark.parametrize("rho", [0.0, 0.3, 0.9, 0.983, 0.999])
def test_mean_variance_matches_the_direct_sum(rho: float) -> None:
    n = np.arange(1, 120)
    expected = np.array([_direct(int(k), rho) for k in n])
    np.testing.assert_allclose(mean_variance(n, rho), expected, rtol=1e-9, atol=1e-12)


def test_mean_variance_limits() -> None:
    np.testing.assert_allclose(mean_variance(np.array([1.0, 4.0, 100.0]), 0.0), [1.0, 0.25, 0.01])
    np.testing.assert_allclose(mean_variance(np.array([1.0, 50.0]), 1.0), [1.0, 1.0])
    # many samples: n V -> the long-run factor (1 + rho) / (1 - rho)
    rho = float(correlation(1.0, 10.0))
    assert 1e5 * float(mean_variance(1e5, rho)) == pytest.approx(float(long_run_factor(rho)), rel=1e-3)


def test_smoothed_variance_matches_a_simulation() -> None:
    """Means of n samples of white + Gauss-Markov errors: their variance is the model's, not 1/n."""
    model = ErrorCorrelation(tau_s=15.0, fraction=0.7)
    rng = np.random.default_rng(3)
    rho = math.exp(-1.0 / model.tau_s)
    runs, length = 4000, 60
    markov = np.zeros((runs, length))
    markov[:, 0] = rng.standard_normal(runs)
    for k in range(1, length):
        markov[:, k] = rho * markov[:, k - 1] + math.sqrt(1 - rho**2) * rng.standard_normal(runs)
    errors = math.sqrt(model.fraction) * markov + math.sqrt(1 - model.fraction) * rng.standard_normal(
        (runs, length)
    )
    for n in (1, 5, 20, 60):
        measured = float(np.var(errors[:, :n].mean(axis=1)))
        assert measured == pytest.approx(float(model.smoothed_variance(np.array([n]), 1.0)[0]), rel=0.08)
        if n > 1:
            assert measured > 2.0 / n  # the white rule would claim 1/n


def test_memory_factors() -> None:
    raw = np.zeros(3)
    np.testing.assert_allclose(memory_factors(raw, 1.0, FITTED_CORRELATION, 1.0), 1.0)
    np.testing.assert_allclose(memory_factors(raw, 3.0, ErrorCorrelation(0.0, 0.0), 1.0), 1.0)
    # fully correlated raw code over M epochs: the average is no better than one epoch, factor M
    np.testing.assert_allclose(memory_factors(raw, 2.5, ErrorCorrelation(1e9, 1.0), 1.0), 2.5, rtol=1e-6)
    # a long Hatch average is nearly the same from epoch to epoch, whatever the raw correlation
    long = memory_factors(np.array([100.0]), 2.0, ErrorCorrelation(0.5, 0.2), 1.0)
    assert 1.9 < float(long[0]) <= 2.0


def _geometry(rng: np.random.Generator, n: int = 8) -> np.ndarray:
    """n line-of-sight rows (north, east, up) above the horizon with a clock column."""
    azimuth = rng.uniform(0, 2 * np.pi, n)
    elevation = rng.uniform(0.2, 1.4, n)
    los = np.column_stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
    )
    return np.column_stack([-los, np.ones(n)])


def test_honest_factor_closed_cases() -> None:
    h = _geometry(np.random.default_rng(1))
    variance = np.linspace(1.0, 4.0, len(h))
    vague = np.eye(2) * 1e9
    factor, memory, own = honest_factor(h, variance, vague, lambda m: variance)
    assert factor == pytest.approx(1.0) and memory == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(own, np.linalg.inv(h.T @ (h / variance[:, None]))[:2, :2])
    assert honest_factor(h, variance, vague, lambda m: 3.0 * variance)[0] == pytest.approx(3.0)
    # a prior as informative as the epoch: the filter averages two epochs
    own = np.linalg.inv(h.T @ (h / variance[:, None]))[:2, :2]
    assert honest_factor(h, variance, own, lambda m: m * variance)[:2] == pytest.approx((2.0, 2.0))
    assert honest_factor(h[:4], variance[:4], vague, lambda m: variance[:4]) is None  # no redundancy


def test_kalman_filter_nees_with_the_factor() -> None:
    """A static receiver's position and clock as random walks, eight satellites with white + Gauss-Markov
    errors (the fitted model, 1 s epochs), a Kalman filter that takes them as white: its horizontal NEES
    is far above 2; its covariance times the memory-and-consider factor gives a mean NEES near 2."""
    rng = np.random.default_rng(5)
    model = ErrorCorrelation(tau_s=20.0, fraction=0.8)
    rho = math.exp(-1.0 / model.tau_s)
    h = _geometry(rng)
    n = len(h)
    variance = np.full(n, 4.0)
    q = np.diag([1.0, 1.0, 1.0, 100.0])
    white, honest = [], []
    for _run in range(40):
        x, p = np.zeros(4), np.eye(4) * 100.0
        truth = np.zeros(4)
        markov = rng.standard_normal(n)
        for epoch in range(120):
            truth = truth + np.sqrt(np.diag(q)) * rng.standard_normal(4)
            markov = rho * markov + math.sqrt(1 - rho**2) * rng.standard_normal(n)
            error = 2.0 * (
                math.sqrt(model.fraction) * markov + math.sqrt(1 - model.fraction) * rng.standard_normal(n)
            )
            z = h @ truth + error
            p_prior = p + q
            result = honest_factor(
                h, variance, p_prior[:2, :2], lambda m: variance * memory_factors(np.zeros(n), m, model, 1.0)
            )
            assert result is not None
            factor = result[0]
            s = h @ p_prior @ h.T + np.diag(variance)
            gain = p_prior @ h.T @ np.linalg.inv(s)
            x = x + gain @ (z - h @ x)
            p = (np.eye(4) - gain @ h) @ p_prior
            if epoch >= 20:
                e = (x - truth)[:2]
                nees = float(e @ np.linalg.solve(p[:2, :2], e))
                white.append(nees)
                honest.append(nees / factor)
    assert np.mean(white) > 3.0
    assert 1.4 < np.mean(honest) < 3.0
