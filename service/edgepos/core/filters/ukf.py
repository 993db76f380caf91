"""Unscented Kalman filter with the scaled sigma-point set (Julier 2002, Wan & van der Merwe 2000).

2m + 1 points: the mean and mean +- sqrt(m + lambda) L e_i, lambda = alpha^2 (m + kappa) - m.
Defaults alpha = 1, beta = 2, kappa = 3 - m (Julier's heuristic, the spread sqrt(3) of a Gaussian's
fourth moment); the centre mean weight is then negative for m > 3, which is why covariances are
re-symmetrised and factorised robustly.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from edgepos.core.errors import ConfigurationError
from edgepos.core.filters.sigma_points import SigmaPointFilter


class UnscentedKalmanFilter(SigmaPointFilter):
    """Scaled unscented transform; ``kappa=None`` means 3 - m for an m-dimensional state."""

    name = "ukf"

    def __init__(self, alpha: float = 1.0, beta: float = 2.0, kappa: float | None = None) -> None:
        if not (np.isfinite(alpha) and alpha > 0.0) or not np.isfinite(beta):
            raise ConfigurationError("UKF alpha must be positive and beta finite")
        if kappa is not None and not np.isfinite(kappa):
            raise ConfigurationError("UKF kappa must be finite")
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), kappa

    def params(self) -> dict[str, Any]:
        return {"alpha": self.alpha, "beta": self.beta, "kappa": self.kappa}

    def unit_points(self, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        kappa = 3.0 - dim if self.kappa is None else float(self.kappa)
        return _scaled_points(dim, self.alpha, self.beta, kappa)


@functools.lru_cache(maxsize=64)
def _scaled_points(dim: int, alpha: float, beta: float, kappa: float):
    spread_sq = alpha * alpha * (dim + kappa)
    if spread_sq <= 0.0:
        raise ConfigurationError(f"UKF alpha^2 (m + kappa) must be positive, got {spread_sq}")
    lam = spread_sq - dim
    offsets = np.vstack([np.zeros(dim), np.sqrt(spread_sq) * np.eye(dim), -np.sqrt(spread_sq) * np.eye(dim)])
    mean_weights = np.full(2 * dim + 1, 1.0 / (2.0 * spread_sq))
    mean_weights[0] = lam / spread_sq
    cov_weights = mean_weights.copy()
    cov_weights[0] += 1.0 - alpha * alpha + beta
    for array in (offsets, mean_weights, cov_weights):
        array.setflags(write=False)
    return offsets, mean_weights, cov_weights
