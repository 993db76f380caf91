"""The UPF's compiled importance weights (core/particles/upf_kernel.py) against the numpy reference they
replace in ``UnscentedParticleFilter.step`` (``Measurement.log_likelihood``, ``gaussian_logpdf``,
``normalise``), and the switch back to numpy with EDGEPOS_NUMBA=0."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import compiled
from edgepos.core.errors import NumericalError
from edgepos.core.particles import upf_kernel
from edgepos.core.particles.base import Measurement, gaussian_logpdf, normalise

pytestmark = pytest.mark.skipif(
    not compiled.compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)"
)


def _factor(rng: np.random.Generator, k: int, scale: float) -> np.ndarray:
    a = rng.normal(size=(k, k))
    return np.linalg.cholesky(scale * (a @ a.T + k * np.eye(k)))


def _case(seed: int, outliers: float, count: int = 200, m: int = 40, k: int = 12):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    variances = np.concatenate([rng.uniform(1.0, 25.0, m // 2), rng.uniform(0.01, 0.1, m - m // 2)])
    outlier_variance = np.concatenate([np.full(m // 2, 900.0), np.full(m - m // 2, 4.0)])
    measurement = Measurement(
        lambda states: states, np.zeros(m), variances, outliers, outlier_variance if outliers else 0.0
    )
    residual = rng.normal(size=(count, m)) * np.sqrt(variances)
    residual[:5] *= 40.0  # a few particles far in the tails, where the mixture's outlier term takes over
    previous = normalise(rng.normal(0.0, 2.0, count))
    prior_chol, proposal_chol = _factor(rng, k, 4.0), _factor(rng, k, 1.0)
    prior_deviation = rng.normal(size=(count, k)) @ prior_chol.T
    proposal_deviation = rng.normal(size=(count, k)) @ proposal_chol.T
    return previous, measurement, residual, prior_deviation, prior_chol, proposal_deviation, proposal_chol


@pytest.mark.parametrize("outliers", [0.0, 0.05])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_kernel_weights_match_the_numpy_reference(outliers: float, seed: int) -> None:
    """The same normalised log-weights to 1e-9 (the sums' order and the C library's exp and log1p against
    numpy's make the difference: about 1e-13 measured), with and without the outlier mixture."""
    previous, measurement, residual, prior_dev, prior_chol, proposal_dev, proposal_chol = _case(
        seed, outliers
    )
    reference = normalise(
        previous
        + measurement.log_likelihood(residual)
        + gaussian_logpdf(prior_dev, prior_chol)
        - gaussian_logpdf(proposal_dev, proposal_chol)
    )
    kernel = upf_kernel.log_weights(
        previous, measurement, residual, prior_dev, prior_chol, proposal_dev, proposal_chol
    )
    assert kernel is not None
    np.testing.assert_allclose(kernel, reference, rtol=0.0, atol=1e-9)
    assert math.isclose(float(np.sum(np.exp(kernel))), 1.0, rel_tol=1e-12)
    assert np.ptp(reference) > 10.0  # the weights differ: the comparison is not of constants


def test_every_particle_lost_raises() -> None:
    previous, measurement, residual, prior_dev, prior_chol, proposal_dev, proposal_chol = _case(4, 0.0)
    previous = np.full(len(previous), -math.inf)
    with pytest.raises(NumericalError):
        upf_kernel.log_weights(
            previous, measurement, residual, prior_dev, prior_chol, proposal_dev, proposal_chol
        )
    previous[7] = math.nan
    with pytest.raises(NumericalError):
        upf_kernel.log_weights(
            previous, measurement, residual, prior_dev, prior_chol, proposal_dev, proposal_chol
        )


def test_reference_when_off_or_per_particle_factors(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """None (the caller's numpy reference runs) with EDGEPOS_NUMBA=0 or per-particle factors."""
    previous, measurement, residual, prior_dev, prior_chol, proposal_dev, proposal_chol = _case(5, 0.05)
    stacked = np.broadcast_to(proposal_chol, (len(previous),) + proposal_chol.shape)
    assert (
        upf_kernel.log_weights(previous, measurement, residual, prior_dev, prior_chol, proposal_dev, stacked)
        is None
    )
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    assert (
        upf_kernel.log_weights(
            previous, measurement, residual, prior_dev, prior_chol, proposal_dev, proposal_chol
        )
        is None
    )
