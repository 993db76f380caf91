"""Odometer over one sampling interval (V2X federated paper, eq. 8, row 2): d = T sqrt(xv^2 + yv^2).

The distance the wheels report over an interval of T seconds, modelled as T times the speed at the
end of the interval, as the paper does. A speed reading is the same model with T = 1 s.
"""

from __future__ import annotations

import numpy as np

from edgepos.core import layout
from edgepos.core.measurements.base import MeasurementModel, Stacked
from edgepos.core.measurements.gyro import GyroYawRate
from edgepos.core.numerics import FloatArray


class OdometerDistance(MeasurementModel):
    """Distance over ``interval`` seconds (m) with noise standard deviation ``std`` (m).

    The speed's gradient is undefined at standstill; below ``min_speed`` it is taken along +x."""

    def __init__(self, std: float, interval: float, min_speed: float = 1e-3) -> None:
        self.std = float(std)
        self.interval = float(interval)
        self.min_speed = float(min_speed)
        self._noise = np.array([[self.std**2]])

    @property
    def dim(self) -> int:
        return 1

    @property
    def angle_mask(self) -> np.ndarray:
        return np.zeros(1, dtype=bool)

    def predict(self, states: np.ndarray) -> np.ndarray:
        distance: FloatArray = (self.interval * np.hypot(states[:, layout.XV], states[:, layout.YV]))[:, None]
        return distance

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        xv, yv = states[:, layout.XV], states[:, layout.YV]
        speed = np.hypot(xv, yv)
        moving = speed > self.min_speed
        safe = np.where(moving, speed, 1.0)
        jacobian = np.zeros((states.shape[0], 1, layout.FULL_DIM))
        jacobian[:, 0, layout.XV] = self.interval * np.where(moving, xv / safe, 1.0)
        jacobian[:, 0, layout.YV] = self.interval * np.where(moving, yv / safe, 0.0)
        return jacobian

    def noise_covariance(self) -> np.ndarray:
        return self._noise


def dead_reckoning(gyro_std: float, odometer_std: float, interval: float) -> Stacked:
    """Eq. 8 whole: gyro yaw rate (rad/s) over odometer distance over ``interval`` (m)."""
    return Stacked([GyroYawRate(gyro_std), OdometerDistance(odometer_std, interval)])
