"""Extended Kalman filter with analytic Jacobians of the motion and measurement models."""

from __future__ import annotations

import numpy as np

from edgepos.core import layout
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

    def predict_measurement(
        self,
        mean: np.ndarray,
        cov: np.ndarray,
        components: tuple[int, ...],
        angle_mask: np.ndarray,
        measurement: MeasurementModel,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        full = layout.embed(mean[None, :], components)
        predicted = measurement.predict(full)[0]
        jacobian = measurement.jacobian(full[0])[:, components]
        cross_cov = cov @ jacobian.T
        innovation_cov = symmetrize(jacobian @ cross_cov + measurement.noise_covariance())
        return predicted, innovation_cov, cross_cov
