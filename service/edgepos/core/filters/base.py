"""The filter contract: every filter predicts with a motion model and updates with a measurement model.

Filters work on a motion model's sub-state (``components``). Measurement models see full 8-dim rows
with zeros for the components a sub-state lacks. All filters share one Gaussian correction
(:func:`kalman_correct`), fed with the predicted measurement, its covariance S and the
state-measurement cross covariance C that each filter computes its own way.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from scipy.linalg import solve_triangular

from edgepos.core.errors import NumericalError
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion.base import MotionModel
from edgepos.core.numerics import require_finite, symmetrize, wrap_rows

_LOG_TWO_PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class UpdateResult:
    """A posterior and the statistics of the innovation that produced it."""

    mean: np.ndarray
    cov: np.ndarray
    innovation: np.ndarray
    innovation_cov: np.ndarray
    nis: float
    log_likelihood: float


class GaussianFilter(ABC):
    """Predict/update on a Gaussian (mean, cov) over a motion model's sub-state."""

    name: ClassVar[str]

    @abstractmethod
    def predict(
        self, mean: np.ndarray, cov: np.ndarray, motion: MotionModel, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Propagate (mean, cov) over ``dt`` seconds with ``motion``."""

    @abstractmethod
    def predict_measurement(
        self,
        mean: np.ndarray,
        cov: np.ndarray,
        components: tuple[int, ...],
        angle_mask: np.ndarray,
        measurement: MeasurementModel,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted measurement z_hat, its covariance S (R included) and the cross covariance C."""

    def params(self) -> dict[str, Any]:
        """Tuning parameters, enough to rebuild the filter with ``cls(**params)``."""
        return {}

    def update(
        self,
        mean: np.ndarray,
        cov: np.ndarray,
        components: tuple[int, ...],
        angle_mask: np.ndarray,
        measurement: MeasurementModel,
        observed: np.ndarray,
    ) -> UpdateResult:
        """Condition (mean, cov) on ``observed`` = h(x) + v."""
        predicted, innovation_cov, cross_cov = self.predict_measurement(
            mean, cov, components, angle_mask, measurement
        )
        residual = measurement.residual(observed, predicted)
        return kalman_correct(mean, cov, angle_mask, residual, innovation_cov, cross_cov)


def kalman_correct(
    mean: np.ndarray,
    cov: np.ndarray,
    angle_mask: np.ndarray,
    residual: np.ndarray,
    innovation_cov: np.ndarray,
    cross_cov: np.ndarray,
) -> UpdateResult:
    """The Kalman correction through the Cholesky factor L of S.

    With U = L^-1 C^T and e = L^-1 r: x+ = x + U^T e, P+ = P - U^T U (= P - K S K^T),
    NIS = e^T e and log|S| = 2 sum(log diag L). One triangular solve, no explicit inverse.
    """
    try:
        chol = np.linalg.cholesky(innovation_cov)
    except np.linalg.LinAlgError:
        raise NumericalError("innovation covariance is not positive definite") from None
    whitened = solve_triangular(
        chol, np.column_stack([cross_cov.T, residual]), lower=True, check_finite=False
    )
    gain_factor, whitened_residual = whitened[:, :-1], whitened[:, -1]
    new_mean = wrap_rows(mean + gain_factor.T @ whitened_residual, angle_mask)
    new_cov = symmetrize(cov - gain_factor.T @ gain_factor)
    nis = float(whitened_residual @ whitened_residual)
    log_det = 2.0 * float(np.sum(np.log(np.diag(chol))))
    log_likelihood = -0.5 * (nis + log_det + residual.size * _LOG_TWO_PI)
    require_finite("updated state", new_mean, new_cov)
    if np.any(np.diag(new_cov) <= 0.0):
        raise NumericalError("updated covariance lost positive variances")
    return UpdateResult(new_mean, new_cov, residual, innovation_cov, nis, log_likelihood)
