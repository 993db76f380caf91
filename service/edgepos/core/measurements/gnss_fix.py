"""A GNSS position fix: the receiver's east/north position in the site frame."""

from __future__ import annotations

import numpy as np

from edgepos.core import layout
from edgepos.core.measurements.base import MeasurementModel


class GnssPosition(MeasurementModel):
    """z = [xp, yp] + v, with 1-sigma ``std`` (m) on each axis, uncorrelated."""

    def __init__(self, std: float) -> None:
        self._noise = np.eye(2) * float(std) ** 2

    @property
    def dim(self) -> int:
        return 2

    @property
    def angle_mask(self) -> np.ndarray:
        return np.zeros(2, dtype=bool)

    def predict(self, states: np.ndarray) -> np.ndarray:
        return states[:, [layout.XP, layout.YP]]

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        jacobian = np.zeros((states.shape[0], 2, layout.FULL_DIM))
        jacobian[:, 0, layout.XP] = 1.0
        jacobian[:, 1, layout.YP] = 1.0
        return jacobian

    def noise_covariance(self) -> np.ndarray:
        return self._noise
