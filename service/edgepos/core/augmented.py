"""Unscented update with uncertain parameters of the measurement augmented into the state.

Qiao & Qu (2021), eqs. 8-26: a vehicle ranging to neighbours does not know where they are, only
their estimates and covariances. The traditional UKF treats those positions as exact; the improved
one appends them to the state, draws sigma points over the joint Gaussian, and updates the joint
mean and covariance, so the neighbours' uncertainty enters the innovation covariance and the gain
with its correlations. Only the vehicle's own block is kept afterwards: the neighbours' blocks are
re-read from their sessions at the next measurement (their own filters own them).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from edgepos.core.errors import NumericalError
from edgepos.core.filters.sigma_points import SigmaPointFilter
from edgepos.core.numerics import require_finite, robust_cholesky, symmetrize


def augmented_update(
    sigma_filter: SigmaPointFilter,
    mean: np.ndarray,
    cov: np.ndarray,
    extra_mean: np.ndarray,
    extra_cov: np.ndarray,
    measure: Callable[[np.ndarray], np.ndarray],
    noise: np.ndarray,
    observed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Update (``mean``, ``cov``) with ``observed`` = measure([state, extra]) + v, v ~ N(0, ``noise``).

    ``extra_mean``/``extra_cov``: the Gaussian of the parameters appended to the state, independent
    of it a priori. ``measure`` maps sigma points (n_points, m + e) to predictions (n_points, k).
    Returns the updated own mean and covariance and the innovation with its covariance.
    """
    own = mean.size
    joint_mean = np.concatenate([mean, extra_mean])
    joint_cov = np.zeros((joint_mean.size, joint_mean.size))
    joint_cov[:own, :own] = cov
    joint_cov[own:, own:] = extra_cov
    offsets, mean_weights, cov_weights = sigma_filter.unit_points(joint_mean.size)
    points = joint_mean + offsets @ robust_cholesky(joint_cov).T
    predicted = measure(points)
    z_mean = mean_weights @ predicted
    z_dev = predicted - z_mean
    x_dev = points - joint_mean
    innovation_cov = symmetrize((z_dev.T * cov_weights) @ z_dev + noise)
    cross = (x_dev.T * cov_weights) @ z_dev
    try:
        factor = np.linalg.cholesky(innovation_cov)
    except np.linalg.LinAlgError:
        raise NumericalError(
            "innovation covariance of the augmented update is not positive definite"
        ) from None
    gain = np.linalg.solve(factor.T, np.linalg.solve(factor, cross.T)).T
    innovation = observed - z_mean
    new_joint_mean = joint_mean + gain @ innovation
    new_joint_cov = symmetrize(joint_cov - gain @ innovation_cov @ gain.T)
    new_mean, new_cov = new_joint_mean[:own], new_joint_cov[:own, :own]
    require_finite("augmented update", new_mean, new_cov)
    return new_mean, new_cov, innovation, innovation_cov
