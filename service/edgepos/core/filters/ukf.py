"""Unscented Kalman filter with the scaled sigma-point set (Julier 2002, Wan & van der Merwe 2000).

2m + 1 points: the mean and mean +- sqrt(m + lambda) L e_i, lambda = alpha^2 (m + kappa) - m.
Defaults alpha = 1, beta = 2, kappa = 3 - m (Julier's heuristic: spread sqrt(3), matching a
Gaussian's fourth moment); the centre mean weight is then negative for m > 3, which is why
covariances are re-symmetrised and factorised robustly.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from edgepos.core.errors import ConfigurationError
from edgepos.core.filters.sigma_points import SigmaPointFilter
from edgepos.core.parameters import ParameterSpec


class UnscentedKalmanFilter(SigmaPointFilter):
    """Scaled unscented transform; ``kappa=None`` means 3 - m for an m-dimensional state."""

    name = "ukf"
    has_centre_point = True
    parameters = (
        ParameterSpec("alpha", "sigma-point spread", 1e-3, 1.0),
        ParameterSpec("beta", "prior-distribution weight of the centre point (2: Gaussian)", 0.0, 10.0),
        ParameterSpec("kappa", "secondary spread; null: 3 - state dimension", -10.0, 100.0, nullable=True),
    )

    def __init__(self, alpha: float = 1.0, beta: float = 2.0, kappa: float | None = None) -> None:
        if not (np.isfinite(alpha) and alpha > 0.0) or not np.isfinite(beta):
            raise ConfigurationError("UKF alpha must be positive and beta finite")
        if kappa is not None and not np.isfinite(kappa):
            raise ConfigurationError("UKF kappa must be finite")
        self.alpha, self.beta = float(alpha), float(beta)
        self.kappa = None if kappa is None else float(kappa)

    def params(self) -> dict[str, Any]:
        return {"alpha": self.alpha, "beta": self.beta, "kappa": self.kappa}

    def point_weights(self, dim: int) -> tuple[float, float, float, float]:
        kappa = 3.0 - dim if self.kappa is None else self.kappa
        spread_sq = self.alpha**2 * (dim + kappa)
        if spread_sq <= 0.0:
            raise ConfigurationError(f"UKF alpha^2 (m + kappa) must be positive, got {spread_sq}")
        centre_mean = (spread_sq - dim) / spread_sq
        centre_cov = centre_mean + 1.0 - self.alpha**2 + self.beta
        return math.sqrt(spread_sq), 1.0 / (2.0 * spread_sq), centre_mean, centre_cov

    def __hash__(self) -> int:
        return hash((self.name, self.alpha, self.beta, self.kappa))

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and other.params() == self.params()
