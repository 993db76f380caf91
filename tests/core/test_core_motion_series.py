"""The closed-form discretisations (integrator chains, Markov chains) against 50-digit references
and against Van Loan: they replace the matrix exponential so that intervals that jitter stay cheap,
so they must be at least as accurate entry by entry, over tiny, paper-sized and long intervals."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core.motion.base import integrator_chain, markov_chain, van_loan
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from tests.core.test_core_motion_closed_forms import exact, singer_f, singer_q


def chain_drift(order: int, rate: float) -> np.ndarray:
    """A = integrator chain whose last state decays at ``rate`` (a Markov chain; rate 0: integrators)."""
    drift = np.diag(np.ones(order - 1), 1)
    drift[-1, -1] = -rate
    return drift


def van_loan_chain(order: int, rate: float, density: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    drift = chain_drift(order, rate)
    noise_density = np.zeros((order, order))
    noise_density[-1, -1] = density
    return van_loan(drift, noise_density, dt)


@pytest.mark.parametrize(
    ("alpha", "dt"),
    [(0.8, 0.05), (0.05, 1e-4), (0.1, 0.01), (0.8, 0.6251), (2.0, 1.0), (0.8, 12.5), (3.0, 40.0)],
)
def test_singer_series_matches_singer_1970_entry_by_entry(alpha: float, dt: float) -> None:
    """Every entry to 1e-12 relative, also the cancelling q11 at alpha T = 5e-6 where Van Loan
    only reaches about 1e-8."""
    sigma = 3.0
    transition, noise = markov_chain(3, alpha, 2.0 * alpha * sigma**2, dt)
    np.testing.assert_allclose(transition, exact(singer_f, alpha, dt), rtol=1e-12, atol=0.0)
    np.testing.assert_allclose(noise, exact(singer_q, alpha, sigma, dt), rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
@pytest.mark.parametrize("dt", [1e-5, 0.05, 1.0, 30.0])
def test_integrator_chain_equals_van_loan(order: int, dt: float) -> None:
    transition, noise = integrator_chain(order, 2.5, dt)
    reference_f, reference_q = van_loan_chain(order, 0.0, 2.5, dt)
    np.testing.assert_allclose(transition, reference_f, rtol=1e-13, atol=0.0)
    # Van Loan is accurate relative to the largest entry only (its tiny corner entries are not).
    np.testing.assert_allclose(noise, reference_q, rtol=1e-9, atol=1e-14 * np.max(reference_q))


def test_zero_rate_is_the_integrator_chain() -> None:
    for order in (2, 3):
        for left, right in zip(markov_chain(order, 0.0, 1.7, 0.3), integrator_chain(order, 1.7, 0.3)):
            np.testing.assert_array_equal(left, right)


@settings(max_examples=150, deadline=None)
@given(
    order=st.integers(2, 4),
    rate=st.floats(1e-6, 20.0),
    dt=st.floats(1e-3, 200.0),
    density=st.floats(1e-6, 1e3),
)
@example(order=2, rate=0.25, dt=61.0, density=872.0)
def test_markov_chain_equals_van_loan_and_is_positive_definite(
    order: int, rate: float, dt: float, density: float
) -> None:
    transition, noise = markov_chain(order, rate, density, dt)
    _, reference_q = van_loan_chain(order, rate, density, dt)
    # F against the drift's own exponential: Van Loan's F shares an exponential with the noise block,
    # whose scale (density x dt^3) leaks into its small entries (order 2, rate 0.25, dt 61, density
    # 872 gave F[1, 0] = -2.5e-13 where the exact value is 0; expm(A dt) gives 0 and F to 4e-16).
    reference_f = expm(chain_drift(order, rate) * dt)
    scale_f, scale_q = np.max(np.abs(reference_f)), np.max(np.abs(reference_q))
    np.testing.assert_allclose(transition, reference_f, rtol=1e-9, atol=1e-13 * scale_f)
    np.testing.assert_allclose(noise, reference_q, rtol=1e-7, atol=1e-12 * scale_q)
    np.testing.assert_array_equal(noise, noise.T)
    assert np.all(np.linalg.eigvalsh(noise / scale_q) > -1e-12)
