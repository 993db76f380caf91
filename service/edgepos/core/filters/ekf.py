"""Extended Kalman filter with analytic Jacobians of the motion and measurement models."""

from __future__ import annotations

import numpy as np

from edgepos.core.filters.base import GaussianFilter
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion.base import MotionModel
from edgepos.core.numerics import require_finite, symmetrize


class ExtendedKalmanFilter(GaussianFilter):
    """First-order linearisation at the current mean."""

    name = "ekf"

    def predict(
        self, mean: np.ndarray, cov: np.ndarray, motion: MotionModel, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        transition = motion.transition_matrix(mean, dt)
        new_mean = motion.propagate(mean[None, :], dt)[0]
        new_cov = symmetrize(transition @ cov @ transition.T + motion.noise_covariance(mean, dt))
        require_finite("predicted state", new_mean, new_cov)
        return new_mean, new_cov

    def measurement_moments(
        self, means: np.ndarray, covs: np.ndarray, active: np.ndarray, measurement: MeasurementModel
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        predicted = measurement.predict(means)
        jacobian = measurement.jacobian(means) * active[:, None, :]
        cross_cov = covs @ jacobian.transpose(0, 2, 1)
        innovation_cov = jacobian @ cross_cov + measurement.noise_covariance()
        return predicted, 0.5 * (innovation_cov + innovation_cov.transpose(0, 2, 1)), cross_cov
