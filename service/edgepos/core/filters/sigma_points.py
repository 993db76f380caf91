"""Sigma-point filters: a deterministic point set carries the Gaussian through f and h.

Subclasses choose the point set (unit directions and weights); the propagation, circular means for
angles and the moment sums are shared. For a motion model that is linear in the state the point
sums equal F P F^T + Q exactly, so that closed form is used: identical in exact arithmetic, cheaper.
"""

from __future__ import annotations

from abc import abstractmethod

import numpy as np

from edgepos.core import layout
from edgepos.core.filters.base import GaussianFilter
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion.base import MotionModel
from edgepos.core.numerics import (
    require_finite,
    robust_cholesky,
    symmetrize,
    weighted_mean,
    wrap_rows,
)


class SigmaPointFilter(GaussianFilter):
    """Predict and update by weighted sums over sigma points."""

    @abstractmethod
    def unit_points(self, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit offsets (n_points, dim) and mean and covariance weights (n_points,)."""

    def sigma_points(self, mean: np.ndarray, cov: np.ndarray, angle_mask: np.ndarray):
        """Points mean + L s_r for the Cholesky factor L of cov, with their weights."""
        offsets, mean_weights, cov_weights = self.unit_points(mean.size)
        points = mean + offsets @ robust_cholesky(cov).T
        return points, mean_weights, cov_weights

    def predict(
        self, mean: np.ndarray, cov: np.ndarray, motion: MotionModel, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        noise = motion.noise_covariance(mean, dt)
        mask = layout.angle_mask(motion.components)
        if motion.linear:
            transition = motion.transition_matrix(mean, dt)
            new_mean = wrap_rows(transition @ mean, mask)
            new_cov = symmetrize(transition @ cov @ transition.T + noise)
        else:
            points, mean_weights, cov_weights = self.sigma_points(mean, cov, mask)
            moved = motion.propagate(points, dt)
            new_mean = weighted_mean(moved, mean_weights, mask)
            deviations = wrap_rows(moved - new_mean, mask)
            new_cov = symmetrize((deviations.T * cov_weights) @ deviations + noise)
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
        points, mean_weights, cov_weights = self.sigma_points(mean, cov, angle_mask)
        predicted_points = measurement.predict(layout.embed(points, components))
        measurement_mask = measurement.angle_mask
        predicted = weighted_mean(predicted_points, mean_weights, measurement_mask)
        z_dev = wrap_rows(predicted_points - predicted, measurement_mask)
        x_dev = wrap_rows(points - mean, angle_mask)
        weighted_z_dev = z_dev.T * cov_weights
        innovation_cov = symmetrize(weighted_z_dev @ z_dev + measurement.noise_covariance())
        cross_cov = (x_dev.T * cov_weights) @ z_dev
        return predicted, innovation_cov, cross_cov
