"""Gyro yaw rate (RSU + IMU paper, eq. 4, row 3): omega = (xv ya - xa yv) / (xv^2 + yv^2).

The rate of turn of the velocity vector, in rad/s, counter-clockwise positive. It is undefined at
standstill, so the squared speed in the denominator is floored at ``min_speed``^2.
"""

from __future__ import annotations

import numpy as np

from edgepos.core import layout
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.numerics import FloatArray


class GyroYawRate(MeasurementModel):
    """Yaw rate with noise standard deviation ``std`` (rad/s)."""

    def __init__(self, std: float, min_speed: float = 0.1) -> None:
        self.std = float(std)
        self.min_speed_sq = float(min_speed) ** 2
        self._noise = np.array([[self.std**2]])

    @property
    def dim(self) -> int:
        return 1

    @property
    def angle_mask(self) -> np.ndarray:
        return np.zeros(1, dtype=bool)

    def predict(self, states: np.ndarray) -> np.ndarray:
        xv, xa, yv, ya = (states[:, i] for i in (layout.XV, layout.XA, layout.YV, layout.YA))
        speed_sq = np.maximum(xv * xv + yv * yv, self.min_speed_sq)
        yaw_rate: FloatArray = ((xv * ya - xa * yv) / speed_sq)[:, None]
        return yaw_rate

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        xv, xa, yv, ya = (states[:, i] for i in (layout.XV, layout.XA, layout.YV, layout.YA))
        raw_speed_sq = xv * xv + yv * yv
        moving = raw_speed_sq > self.min_speed_sq
        speed_sq = np.where(moving, raw_speed_sq, self.min_speed_sq)
        cross_term = np.where(moving, 2.0 * (xv * ya - xa * yv) / speed_sq**2, 0.0)
        jacobian = np.zeros((states.shape[0], 1, layout.FULL_DIM))
        jacobian[:, 0, layout.XA] = -yv / speed_sq
        jacobian[:, 0, layout.YA] = xv / speed_sq
        jacobian[:, 0, layout.XV] = ya / speed_sq - xv * cross_term
        jacobian[:, 0, layout.YV] = -xa / speed_sq - yv * cross_term
        return jacobian

    def noise_covariance(self) -> np.ndarray:
        return self._noise
