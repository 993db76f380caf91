"""Singer (1970): acceleration as a zero-mean first-order Markov process on the kinematic states."""

from __future__ import annotations

from typing import Any

import numpy as np

from edgepos.core import layout
from edgepos.core.motion.base import LinearAxisModel, check_positive, markov_chain
from edgepos.core.parameters import ParameterSpec


def singer_drift(alpha: float) -> np.ndarray:
    """Per-axis drift of [p, v, a] with da = -alpha a dt + dw."""
    return np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -alpha]])


class Singer(LinearAxisModel):
    """Acceleration with time constant 1/alpha (1/s) and standard deviation sigma (m/s^2).

    The driving noise density is 2 alpha sigma^2, so the stationary acceleration variance is sigma^2.
    """

    name = "singer"
    components = layout.KINEMATIC
    parameters = (
        ParameterSpec("alpha", "manoeuvre frequency 1/tau, 1/s", 1e-4, 100.0),
        ParameterSpec("sigma", "acceleration std, m/s^2", 1e-4, 100.0),
    )

    def __init__(self, alpha: float = 0.8, sigma: float = 5.0) -> None:
        self.alpha = check_positive("alpha", alpha)
        self.sigma = check_positive("sigma", sigma)

    def axis_drift(self) -> np.ndarray:
        return singer_drift(self.alpha)

    def axis_noise_density(self) -> np.ndarray:
        return np.diag([0.0, 0.0, 2.0 * self.alpha * self.sigma**2])

    def axis_exact(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return markov_chain(3, self.alpha, 2.0 * self.alpha * self.sigma**2, dt)

    def params(self) -> dict[str, Any]:
        return {"alpha": self.alpha, "sigma": self.sigma}
