"""Constant velocity on [xp, xv, yp, yv]."""

from __future__ import annotations

from typing import Any

import numpy as np

from edgepos.core import layout
from edgepos.core.motion.base import (
    NOISE_PARAMETER,
    Q_PARAMETER,
    LinearAxisModel,
    check_noise_form,
    check_positive,
    discrete_noise,
    integrator_chain,
)


class ConstantVelocity(LinearAxisModel):
    """Nearly constant velocity.

    ``noise="discrete"`` (default): the acceleration is held constant over each interval, a fresh
    N(0, q^2) draw per axis (q in m/s^2: the paper's process-noise gain). ``"continuous"``: white
    acceleration of power spectral density q (m^2/s^3), discretised exactly.
    """

    name = "cv"
    components = layout.POSITION_VELOCITY
    parameters = (Q_PARAMETER, NOISE_PARAMETER)

    def __init__(self, q: float = 3.5, noise: str = "discrete") -> None:
        self.q = check_positive("q", q)
        self.noise = check_noise_form(noise)

    def axis_drift(self) -> np.ndarray:
        return np.array([[0.0, 1.0], [0.0, 0.0]])

    def axis_noise_density(self) -> np.ndarray:
        return np.diag([0.0, self.q])

    def axis_discrete_noise(self, dt: float) -> np.ndarray | None:
        return discrete_noise(self.q, 2, dt) if self.noise == "discrete" else None

    def axis_exact(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return integrator_chain(2, self.q, dt)

    def params(self) -> dict[str, Any]:
        return {"q": self.q, "noise": self.noise}
