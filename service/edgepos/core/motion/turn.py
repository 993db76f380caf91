"""Coordinated-turn algebra shared by the fixed-rate CT and the adaptive-turn AT models.

The 6-state turn transition on [xp, xv, xa, yp, yv, ya] rotates the velocity at rate omega and
ties the acceleration to it (a = omega x v): the classic form the RSU + IMU paper relies on but
does not write out.

Process noise, per axis (the velocity noise is what lets a turn model follow a change of speed,
since the tie leaves no other way):
- "discrete" (default): the paper's gain q (m/s^2) on G = [T^2/2, T, 1], Q = q^2 G G^T: one
  acceleration draw per interval, as in the CA model (DWPA);
- "continuous": white acceleration of intensity q (m^2/s^3), exact for position and velocity
  (q [[T^3/3, T^2/2], [T^2/2, T]]), plus an independent perturbation q T of the tied acceleration,
  which keeps the covariance positive definite since the transition maps acceleration from velocity.
"""

from __future__ import annotations

import functools

import numpy as np

from edgepos.core.motion.base import discrete_noise, two_axes

#: Below this |omega T| the trigonometric ratios are evaluated by their Taylor series.
_SMALL_TURN = 1e-4


def turn_coefficients(omega: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
    """sin(wT), cos(wT), sin(wT)/w and (1 - cos(wT))/w, exact and stable as w -> 0 (vectorised).

    With sinc(u) = sin(pi u)/(pi u): sin(wT)/w = T sinc(wT/pi) and (1 - cos(wT))/w =
    2 sin^2(wT/2)/w = (w T^2 / 2) sinc^2(wT/(2 pi)); numpy's sinc is exact at 0.
    """
    omega = np.asarray(omega, dtype=float)
    angle = omega * dt
    half_sinc = np.sinc(angle / (2.0 * np.pi))
    return np.sin(angle), np.cos(angle), dt * np.sinc(angle / np.pi), 0.5 * angle * dt * half_sinc * half_sinc


@functools.lru_cache(maxsize=256)
def turn_noise(q: float, noise_form: str, dt: float) -> np.ndarray:
    """Q of the turn models on [xp, xv, xa, yp, yv, ya] for gain or intensity ``q``."""
    if noise_form == "discrete":
        axis = discrete_noise(q, 3, dt)
    else:
        axis = q * np.array(
            [[dt * dt * dt / 3.0, dt * dt / 2.0, 0.0], [dt * dt / 2.0, dt, 0.0], [0.0, 0.0, dt]]
        )
    noise = two_axes(axis)
    noise.setflags(write=False)
    return noise


def turn_propagate(kinematic: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """Apply the turn transition to rows of [xp, xv, xa, yp, yv, ya] with per-row ``omega``."""
    sin, cos, sin_over, one_minus_cos_over = turn_coefficients(omega, dt)
    xp, xv, yp, yv = kinematic[:, 0], kinematic[:, 1], kinematic[:, 3], kinematic[:, 4]
    out = np.empty_like(kinematic)
    vx_new = cos * xv - sin * yv
    vy_new = sin * xv + cos * yv
    out[:, 0] = xp + sin_over * xv - one_minus_cos_over * yv
    out[:, 1] = vx_new
    out[:, 2] = -omega * vy_new
    out[:, 3] = yp + one_minus_cos_over * xv + sin_over * yv
    out[:, 4] = vy_new
    out[:, 5] = omega * vx_new
    return out


def turn_matrix(omega: float, dt: float) -> np.ndarray:
    """The 6x6 turn transition matrix for a fixed turn rate."""
    sin, cos, sin_over, one_minus_cos_over = (float(v) for v in turn_coefficients(np.array(omega), dt))
    return np.array(
        [
            [1.0, sin_over, 0.0, 0.0, -one_minus_cos_over, 0.0],
            [0.0, cos, 0.0, 0.0, -sin, 0.0],
            [0.0, -omega * sin, 0.0, 0.0, -omega * cos, 0.0],
            [0.0, one_minus_cos_over, 0.0, 1.0, sin_over, 0.0],
            [0.0, sin, 0.0, 0.0, cos, 0.0],
            [0.0, omega * cos, 0.0, 0.0, -omega * sin, 0.0],
        ]
    )


def turn_matrix_omega_derivative(kinematic: np.ndarray, omega: float, dt: float) -> np.ndarray:
    """d/d(omega) of turn_matrix(omega) @ kinematic, the extra Jacobian column of AT."""
    angle = omega * dt
    sin, cos = np.sin(angle), np.cos(angle)
    if abs(angle) < _SMALL_TURN:
        d_sin_over = -omega * dt**3 / 3.0
        d_one_minus_cos_over = 0.5 * dt * dt * (1.0 - angle * angle / 4.0)
    else:
        d_sin_over = (dt * cos * omega - sin) / omega**2
        d_one_minus_cos_over = (dt * sin * omega - (1.0 - cos)) / omega**2
    xv, yv = kinematic[1], kinematic[4]
    d_cos, d_sin = -dt * sin, dt * cos
    d_vx = d_cos * xv - d_sin * yv
    d_vy = d_sin * xv + d_cos * yv
    vx_new = cos * xv - sin * yv
    vy_new = sin * xv + cos * yv
    return np.array(
        [
            d_sin_over * xv - d_one_minus_cos_over * yv,
            d_vx,
            -vy_new - omega * d_vy,
            d_one_minus_cos_over * xv + d_sin_over * yv,
            d_vy,
            vx_new + omega * d_vx,
        ]
    )
