"""Coordinated turn at a fixed, known turn rate on the kinematic states."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from edgepos.core import layout
from edgepos.core.errors import ConfigurationError
from edgepos.core.motion.base import (
    NOISE_PARAMETER,
    Q_PARAMETER,
    MotionModel,
    check_noise_form,
    check_positive,
    dt_key,
)
from edgepos.core.motion.turn import turn_matrix, turn_noise
from edgepos.core.numerics import FloatArray
from edgepos.core.parameters import ParameterSpec


class CoordinatedTurn(MotionModel):
    """Velocity rotates at ``omega`` rad/s (counter-clockwise positive); noise ``q`` as in ``turn``."""

    name = "ct"
    components = layout.KINEMATIC
    linear = True
    parameters = (
        Q_PARAMETER,
        ParameterSpec("omega", "turn rate, rad/s, counter-clockwise positive", -2.0 * math.pi, 2.0 * math.pi),
        NOISE_PARAMETER,
    )

    def __init__(self, q: float = 3.5, omega: float = math.radians(20.0), noise: str = "discrete") -> None:
        self.q = check_positive("q", q)
        self.noise = check_noise_form(noise)
        self.omega = float(omega)
        if not math.isfinite(self.omega):
            raise ConfigurationError("omega must be finite")

    def params(self) -> dict[str, Any]:
        return {"q": self.q, "omega": self.omega, "noise": self.noise}

    def propagate(self, points: np.ndarray, dt: float) -> np.ndarray:
        propagated: FloatArray = points @ self.transition_matrix(points[0], dt).T
        return propagated

    def transition_matrix(self, mean: np.ndarray, dt: float) -> np.ndarray:
        return _turn_matrix_cached(self.omega, dt_key(dt))

    def noise_covariance(self, mean: np.ndarray, dt: float) -> np.ndarray:
        return turn_noise(self.q, self.noise, dt_key(dt))


@functools.lru_cache(maxsize=256)
def _turn_matrix_cached(omega: float, dt: float) -> np.ndarray:
    matrix = turn_matrix(omega, dt)
    matrix.setflags(write=False)
    return matrix
