"""Sigma-point filters: a deterministic point set carries the Gaussian through f and h.

Subclasses give the point set for an m-dimensional Gaussian as a spread and weights; propagation,
circular means for angles and the moment sums are shared. For a motion model that is linear in the
state the point sums equal F P F^T + Q exactly, so that closed form is used: identical in exact
arithmetic, cheaper.

In a bank update each Gaussian keeps its own dimension m (the components its model carries): its
Cholesky factor is taken on the active block (inactive diagonal padded with ones, then those columns
zeroed), and the directions of inactive components get zero weight.
"""

from __future__ import annotations

import functools
from abc import abstractmethod

import numpy as np

from edgepos.core import layout
from edgepos.core.filters.base import GaussianFilter
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion.base import MotionModel
from edgepos.core.numerics import (
    FloatArray,
    require_finite,
    robust_cholesky,
    symmetrize,
    weighted_mean,
    wrap_angle,
    wrap_rows,
)


class SigmaPointFilter(GaussianFilter):
    """Predict and update by weighted sums over sigma points."""

    #: True when the point set includes the mean itself as a first point.
    has_centre_point: bool = False

    @abstractmethod
    def point_weights(self, dim: int) -> tuple[float, float, float, float]:
        """For dimension m: spread s (points mean +- s L e_i), the weight of each +-point, and the
        centre point's mean and covariance weights (zero when there is no centre point)."""

    def unit_points(self, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit offsets (n_points, dim) and mean and covariance weights (n_points,) (cached)."""
        return _unit_points(self, dim)

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
            offsets, mean_weights, cov_weights = self.unit_points(mean.size)
            points = mean + offsets @ robust_cholesky(cov).T
            moved = motion.propagate(points, dt)
            new_mean = weighted_mean(moved, mean_weights, mask)
            deviations = wrap_rows(moved - new_mean, mask)
            new_cov = symmetrize((deviations.T * cov_weights) @ deviations + noise)
        require_finite("predicted state", new_mean, new_cov)
        return new_mean, new_cov

    def bank_points(
        self, means: np.ndarray, covs: np.ndarray, active: np.ndarray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Sigma points of every Gaussian of a bank: offsets (B, n, 8), mean and cov weights (B, n)."""
        pad, column_scale, mean_weights, cov_weights = _bank_weights(self, active.tobytes(), active.shape)
        padded = covs + pad
        try:
            factors = np.linalg.cholesky(padded)
        except np.linalg.LinAlgError:
            factors = np.stack([robust_cholesky(c) for c in padded])
        directions = factors.transpose(0, 2, 1) * column_scale  # row i = s * L e_i, zero if inactive
        offsets = np.concatenate([directions, -directions], axis=1)
        if self.has_centre_point:
            offsets = np.concatenate([np.zeros((means.shape[0], 1, layout.FULL_DIM)), offsets], axis=1)
        return offsets, mean_weights, cov_weights

    def measurement_moments(
        self, means: np.ndarray, covs: np.ndarray, active: np.ndarray, measurement: MeasurementModel
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        offsets, mean_weights, cov_weights = self.bank_points(means, covs, active)
        count, points = offsets.shape[:2]
        z = measurement.predict((means[:, None, :] + offsets).reshape(count * points, -1)).reshape(
            count, points, -1
        )
        predicted = (mean_weights[:, None, :] @ z)[:, 0, :]
        angles = measurement.angle_rows
        if angles.size:
            angle_points = z[:, :, angles]
            predicted[:, angles] = np.arctan2(
                (mean_weights[:, None, :] @ np.sin(angle_points))[:, 0, :],
                (mean_weights[:, None, :] @ np.cos(angle_points))[:, 0, :],
            )
        z_dev = z - predicted[:, None, :]
        if angles.size:
            z_dev[:, :, angles] = wrap_angle(z_dev[:, :, angles])
        weighted = z_dev * cov_weights[:, :, None]
        innovation_cov = weighted.transpose(0, 2, 1) @ z_dev + measurement.noise_covariance()
        cross_cov = offsets.transpose(0, 2, 1) @ weighted
        return predicted, 0.5 * (innovation_cov + innovation_cov.transpose(0, 2, 1)), cross_cov


@functools.lru_cache(maxsize=64)
def _unit_points(filt: SigmaPointFilter, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    spread, weight, centre_mean, centre_cov = filt.point_weights(dim)
    offsets = spread * np.vstack([np.eye(dim), -np.eye(dim)])
    mean_weights = np.full(2 * dim, weight)
    cov_weights = mean_weights.copy()
    if filt.has_centre_point:
        offsets = np.vstack([np.zeros(dim), offsets])
        mean_weights = np.concatenate([[centre_mean], mean_weights])
        cov_weights = np.concatenate([[centre_cov], cov_weights])
    for array in (offsets, mean_weights, cov_weights):
        array.setflags(write=False)
    return offsets, mean_weights, cov_weights


@functools.lru_cache(maxsize=256)
def _bank_weights(
    filt: SigmaPointFilter, active_key: bytes, shape: tuple[int, int]
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """For a bank's active pattern (cached): the identity padding of inactive diagonals, the spread
    of each direction (zero for inactive ones), and padded mean and covariance weights."""
    active = np.frombuffer(active_key, dtype=bool).reshape(shape)
    pad = np.eye(shape[1]) * ~active[:, None, :]
    spreads, mean_rows, cov_rows = [], [], []
    for row in active:
        spread, weight, centre_mean, centre_cov = filt.point_weights(int(row.sum()))
        side = np.where(row, weight, 0.0)
        centre = ([centre_mean], [centre_cov]) if filt.has_centre_point else ([], [])
        spreads.append(spread)
        mean_rows.append(np.concatenate([centre[0], side, side]))
        cov_rows.append(np.concatenate([centre[1], side, side]))
    column_scale = (np.array(spreads)[:, None] * active)[:, :, None]
    return pad, column_scale, np.array(mean_rows), np.array(cov_rows)
