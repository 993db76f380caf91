"""Constant velocity (white-noise acceleration) on [xp, xv, yp, yv]."""

from __future__ import annotations

import numpy as np

from edgepos.core import layout
from edgepos.core.motion.base import LinearAxisModel, check_positive


class ConstantVelocity(LinearAxisModel):
    """Velocity is a Wiener process: acceleration is white noise of density ``q`` (m^2/s^3)."""

    name = "cv"
    components = layout.POSITION_VELOCITY

    def __init__(self, q: float = 3.5) -> None:
        self.q = check_positive("q", q)

    def axis_drift(self) -> np.ndarray:
        return np.array([[0.0, 1.0], [0.0, 0.0]])

    def axis_noise_density(self) -> np.ndarray:
        return np.diag([0.0, self.q])

    def params(self) -> dict[str, float]:
        return {"q": self.q}
