"""The adaptive-turn (AT) model of the RSU + IMU paper (eqs. 5-9) on the full 8-dim state.

The turn rate omega is a first-order Markov (Ornstein-Uhlenbeck) state with autocorrelation
eta^2 exp(-beta |tau|); heading phi integrates it. The kinematic block follows the coordinated
turn at the *current* omega, which makes the model nonlinear. Transition (eq. 7):
A = diag{F_CT(omega), F_omega}, F_omega = [[1, (1 - e^{-beta T}) / beta], [0, e^{-beta T}]];
noise (eqs. 8-9): diag{Q_CT, Q_omega}, Q_omega = 2 beta eta^2 [q_ij].
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from edgepos.core import layout
from edgepos.core.motion.base import (
    NOISE_PARAMETER,
    Q_PARAMETER,
    MotionModel,
    check_noise_form,
    check_positive,
    dt_key,
    markov_chain,
)
from edgepos.core.motion.turn import turn_matrix, turn_matrix_omega_derivative, turn_noise, turn_propagate
from edgepos.core.numerics import wrap_angle
from edgepos.core.parameters import ParameterSpec


class AdaptiveTurn(MotionModel):
    """Coordinated turn whose rate is estimated: beta (1/s) is the manoeuvre frequency, eta (rad/s)."""

    name = "at"
    components = layout.ALL
    linear = False
    parameters = (
        Q_PARAMETER,
        ParameterSpec("beta", "turn-rate manoeuvre frequency, 1/s", 1e-4, 100.0),
        ParameterSpec("eta", "turn-rate std, rad/s", 1e-6, 10.0),
        NOISE_PARAMETER,
    )

    def __init__(
        self, q: float = 3.5, beta: float = 0.02, eta: float = 0.17, noise: str = "discrete"
    ) -> None:
        self.q = check_positive("q", q)
        self.noise = check_noise_form(noise)
        self.beta = check_positive("beta", beta)
        self.eta = check_positive("eta", eta)

    def params(self) -> dict[str, Any]:
        return {"q": self.q, "beta": self.beta, "eta": self.eta, "noise": self.noise}

    def turn_rate_block(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """F_omega (eq. 7) and Q_omega (eq. 9) for [phi, omega], exact for the OU turn rate."""
        return _turn_rate_block(self.beta, self.eta, dt_key(dt))

    def propagate(self, points: np.ndarray, dt: float) -> np.ndarray:
        omega = points[:, layout.OMEGA]
        out = np.empty_like(points)
        out[:, :6] = turn_propagate(points[:, :6], omega, dt)
        f_omega, _ = self.turn_rate_block(dt)
        out[:, 6:] = points[:, 6:] @ f_omega.T
        out[:, layout.PHI] = wrap_angle(out[:, layout.PHI])
        return out

    def transition_matrix(self, mean: np.ndarray, dt: float) -> np.ndarray:
        omega = float(mean[layout.OMEGA])
        jacobian = np.zeros((8, 8))
        jacobian[:6, :6] = turn_matrix(omega, dt)
        jacobian[:6, layout.OMEGA] = turn_matrix_omega_derivative(mean[:6], omega, dt)
        jacobian[6:, 6:] = self.turn_rate_block(dt)[0]
        return jacobian

    def noise_covariance(self, mean: np.ndarray, dt: float) -> np.ndarray:
        return _at_noise(self.q, self.noise, self.beta, self.eta, dt_key(dt))


@functools.lru_cache(maxsize=256)
def _turn_rate_block(beta: float, eta: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    transition, noise = markov_chain(2, beta, 2.0 * beta * eta * eta, dt)
    transition.setflags(write=False)
    noise.setflags(write=False)
    return transition, noise


@functools.lru_cache(maxsize=256)
def _at_noise(q: float, noise_form: str, beta: float, eta: float, dt: float) -> np.ndarray:
    noise = np.zeros((8, 8))
    noise[:6, :6] = turn_noise(q, noise_form, dt)
    noise[6:, 6:] = _turn_rate_block(beta, eta, dt)[1]
    noise.setflags(write=False)
    return noise
