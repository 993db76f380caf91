"""Roadside-unit range and bearing to the vehicle (RSU + IMU paper, eq. 4, rows 1-2).

For an RSU at (x_i, y_i): range = hypot(xp - x_i, yp - y_i) in metres, and bearing =
atan2(yp - y_i, xp - x_i) in radians: the direction from the RSU to the vehicle, counter-clockwise
from the +x (east) axis, in [-pi, pi). Several RSUs are handled in one vectorised block with rows
[range_1, bearing_1, range_2, bearing_2, ...].
"""

from __future__ import annotations

import numpy as np

from edgepos.core import layout
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.numerics import FloatArray

#: Below this distance (m) the Jacobians are evaluated at this distance instead.
_MIN_DISTANCE = 1e-3


def _offsets(states: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vehicle minus RSU position, (n, K) each, and the distance floored at _MIN_DISTANCE."""
    dx = states[:, layout.XP, None] - positions[:, 0]
    dy = states[:, layout.YP, None] - positions[:, 1]
    return dx, dy, np.maximum(np.hypot(dx, dy), _MIN_DISTANCE)


class RsuRangeBearing(MeasurementModel):
    """Range and bearing from ``positions`` (K, 2) with per-RSU noise standard deviations."""

    def __init__(self, positions: np.ndarray, range_std: np.ndarray, bearing_std: np.ndarray) -> None:
        self.positions: FloatArray = np.atleast_2d(np.asarray(positions, dtype=float))
        count = self.positions.shape[0]
        variances = np.empty(2 * count)
        variances[0::2] = np.square(range_std)
        variances[1::2] = np.square(bearing_std)
        self._noise = np.diag(variances)
        self._mask = np.zeros(2 * count, dtype=bool)
        self._mask[1::2] = True

    @property
    def dim(self) -> int:
        count: int = self.positions.shape[0]
        return 2 * count

    @property
    def angle_mask(self) -> np.ndarray:
        return self._mask

    def predict(self, states: np.ndarray) -> np.ndarray:
        dx = states[:, layout.XP, None] - self.positions[:, 0]
        dy = states[:, layout.YP, None] - self.positions[:, 1]
        out = np.empty((states.shape[0], self.dim))
        out[:, 0::2] = np.hypot(dx, dy)
        out[:, 1::2] = np.arctan2(dy, dx)
        return out

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        dx, dy, distance = _offsets(states, self.positions)
        jacobian = np.zeros((states.shape[0], self.dim, layout.FULL_DIM))
        jacobian[:, 0::2, layout.XP] = dx / distance
        jacobian[:, 0::2, layout.YP] = dy / distance
        jacobian[:, 1::2, layout.XP] = -dy / distance**2
        jacobian[:, 1::2, layout.YP] = dx / distance**2
        return jacobian

    def noise_covariance(self) -> np.ndarray:
        return self._noise


class RsuRange(MeasurementModel):
    """Range only from ``positions`` (K, 2): time-of-flight ranging to known nodes."""

    def __init__(self, positions: np.ndarray, range_std: np.ndarray) -> None:
        self.positions: FloatArray = np.atleast_2d(np.asarray(positions, dtype=float))
        count = self.positions.shape[0]
        self._noise = np.diag(np.broadcast_to(np.asarray(range_std, dtype=float), (count,)) ** 2)
        self._mask = np.zeros(count, dtype=bool)

    @property
    def dim(self) -> int:
        count: int = self.positions.shape[0]
        return count

    @property
    def angle_mask(self) -> np.ndarray:
        return self._mask

    def predict(self, states: np.ndarray) -> np.ndarray:
        dx = states[:, layout.XP, None] - self.positions[:, 0]
        dy = states[:, layout.YP, None] - self.positions[:, 1]
        return np.hypot(dx, dy)

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        dx, dy, distance = _offsets(states, self.positions)
        jacobian = np.zeros((states.shape[0], self.dim, layout.FULL_DIM))
        jacobian[:, :, layout.XP] = dx / distance
        jacobian[:, :, layout.YP] = dy / distance
        return jacobian

    def noise_covariance(self) -> np.ndarray:
        return self._noise
