"""The "current statistical" model (Zhou & Kumar 1984) on the kinematic states.

Acceleration is a Singer process around a non-zero mean equal to the current acceleration
estimate, with a variance that adapts to how far that estimate is from the manoeuvre limit:
sigma^2 = (4 - pi) / pi * (a_max - |a_hat|)^2.

With the mean taken as the previous acceleration estimate, the Singer transition plus its
mean-input term collapses exactly to the constant-acceleration transition, so F is the CA matrix
and only Q (Singer's form, scaled by the adaptive variance per axis) depends on the state.
"""

from __future__ import annotations

import functools
import math
from typing import Any, ClassVar

import numpy as np

from edgepos.core import layout
from edgepos.core.motion.base import MotionModel, check_positive, dt_key, van_loan
from edgepos.core.motion.singer import singer_drift
from edgepos.core.numerics import FloatArray
from edgepos.core.parameters import ParameterSpec

_CA_DRIFT = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
_RAYLEIGH_FACTOR = (4.0 - math.pi) / math.pi


class CurrentStatistical(MotionModel):
    """Adaptive-variance mean-jerk model; ``a_max`` bounds the manoeuvre acceleration (m/s^2)."""

    name = "current_statistical"
    components = layout.KINEMATIC
    linear: ClassVar[bool] = True
    state_dependent_noise: ClassVar[bool] = True
    parameters = (
        ParameterSpec("alpha", "manoeuvre frequency 1/tau, 1/s", 1e-4, 100.0),
        ParameterSpec("a_max", "largest manoeuvre acceleration, m/s^2", 0.1, 100.0),
        ParameterSpec("sigma_min", "smallest acceleration std, m/s^2", 1e-4, 100.0),
    )

    def __init__(self, alpha: float = 0.8, a_max: float = 5.0, sigma_min: float = 0.1) -> None:
        self.alpha = check_positive("alpha", alpha)
        self.a_max = check_positive("a_max", a_max)
        self.sigma_min = check_positive("sigma_min", sigma_min)

    def params(self) -> dict[str, Any]:
        return {"alpha": self.alpha, "a_max": self.a_max, "sigma_min": self.sigma_min}

    def acceleration_variance(self, acceleration: float) -> float:
        """sigma^2 of the acceleration around its current mean ``acceleration``."""
        margin = max(self.a_max - abs(acceleration), self.sigma_min)
        return _RAYLEIGH_FACTOR * margin * margin

    def propagate(self, points: np.ndarray, dt: float) -> np.ndarray:
        propagated: FloatArray = points @ _ca_transition(dt_key(dt)).T
        return propagated

    def transition_matrix(self, mean: np.ndarray, dt: float) -> np.ndarray:
        return _ca_transition(dt_key(dt))

    def noise_covariance(self, mean: np.ndarray, dt: float) -> np.ndarray:
        unit = _singer_unit_noise(self.alpha, dt_key(dt))
        noise = np.zeros((6, 6))
        noise[:3, :3] = unit * self.acceleration_variance(float(mean[2]))
        noise[3:, 3:] = unit * self.acceleration_variance(float(mean[5]))
        return noise


@functools.lru_cache(maxsize=256)
def _ca_transition(dt: float) -> np.ndarray:
    axis, _ = van_loan(_CA_DRIFT, np.zeros((3, 3)), dt)
    transition = np.kron(np.eye(2), axis)
    transition.setflags(write=False)
    return transition


@functools.lru_cache(maxsize=256)
def _singer_unit_noise(alpha: float, dt: float) -> np.ndarray:
    _, noise = van_loan(singer_drift(alpha), np.diag([0.0, 0.0, 2.0 * alpha]), dt)
    noise.setflags(write=False)
    return noise
