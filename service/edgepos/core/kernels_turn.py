"""Compiled (numba) prediction of the adaptive-turn model (``core.motion.at``) for the bank kernels of
``core.kernels``: its transition at the state's own turn rate, the transition's Jacobian (EKF) and the
sigma-point prediction over all 8 components (CKF, UKF). The same equations as the numpy reference."""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.kernels_base import (
    _OMEGA,
    _PHI,
    _SMALL_TURN,
    _XA,
    _XP,
    _XV,
    _YA,
    _YP,
    _YV,
    _jit,
    _sinc,
    _symmetrize,
    cholesky,
    wrap,
)
from edgepos.core.numerics import FloatArray


@_jit
def _turn_coefficients(omega: float, dt: float) -> tuple[float, float, float, float]:
    angle = omega * dt
    half_sinc = _sinc(angle / (2.0 * math.pi))
    return (
        math.sin(angle),
        math.cos(angle),
        dt * _sinc(angle / math.pi),
        0.5 * angle * dt * half_sinc * half_sinc,
    )


@_jit
def _turn_propagate(state: FloatArray, f_omega: FloatArray, dt: float, out: FloatArray) -> None:
    """The adaptive-turn transition of one full state (``AdaptiveTurn.propagate``)."""
    omega = state[_OMEGA]
    sin, cos, sin_over, one_minus_cos_over = _turn_coefficients(omega, dt)
    xp, xv, yp, yv = state[_XP], state[_XV], state[_YP], state[_YV]
    vx_new = cos * xv - sin * yv
    vy_new = sin * xv + cos * yv
    out[_XP] = xp + sin_over * xv - one_minus_cos_over * yv
    out[_XV] = vx_new
    out[_XA] = -omega * vy_new
    out[_YP] = yp + one_minus_cos_over * xv + sin_over * yv
    out[_YV] = vy_new
    out[_YA] = omega * vx_new
    phi, rate = state[_PHI], state[_OMEGA]
    out[_PHI] = wrap(f_omega[0, 0] * phi + f_omega[0, 1] * rate)
    out[_OMEGA] = f_omega[1, 0] * phi + f_omega[1, 1] * rate


@_jit
def _turn_jacobian(state: FloatArray, f_omega: FloatArray, dt: float, out: FloatArray) -> None:
    """``AdaptiveTurn.transition_matrix``: the turn matrix at the state's omega, its omega column."""
    omega = state[_OMEGA]
    sin, cos, sin_over, one_minus_cos_over = _turn_coefficients(omega, dt)
    out[:, :] = 0.0
    out[_XP, _XP], out[_XP, _XV], out[_XP, _YV] = 1.0, sin_over, -one_minus_cos_over
    out[_XV, _XV], out[_XV, _YV] = cos, -sin
    out[_XA, _XV], out[_XA, _YV] = -omega * sin, -omega * cos
    out[_YP, _XV], out[_YP, _YP], out[_YP, _YV] = one_minus_cos_over, 1.0, sin_over
    out[_YV, _XV], out[_YV, _YV] = sin, cos
    out[_YA, _XV], out[_YA, _YV] = omega * cos, -omega * sin
    angle = omega * dt
    s, c = math.sin(angle), math.cos(angle)
    if abs(angle) < _SMALL_TURN:
        d_sin_over = -omega * dt**3 / 3.0
        d_one_minus_cos_over = 0.5 * dt * dt * (1.0 - angle * angle / 4.0)
    else:
        d_sin_over = (dt * c * omega - s) / omega**2
        d_one_minus_cos_over = (dt * s * omega - (1.0 - c)) / omega**2
    xv, yv = state[_XV], state[_YV]
    d_cos, d_sin = -dt * s, dt * c
    d_vx = d_cos * xv - d_sin * yv
    d_vy = d_sin * xv + d_cos * yv
    out[_XP, _OMEGA] = d_sin_over * xv - d_one_minus_cos_over * yv
    out[_XV, _OMEGA] = d_vx
    out[_XA, _OMEGA] = -(s * xv + c * yv) - omega * d_vy
    out[_YP, _OMEGA] = d_one_minus_cos_over * xv + d_sin_over * yv
    out[_YV, _OMEGA] = d_vy
    out[_YA, _OMEGA] = (c * xv - s * yv) + omega * d_vx
    for i in range(2):
        for j in range(2):
            out[6 + i, 6 + j] = f_omega[i, j]


@_jit
def _turn_predict_sigma(
    mean: FloatArray,
    cov: FloatArray,
    f_omega: FloatArray,
    noise: FloatArray,
    dt: float,
    spread: float,
    side: float,
    centre_mean: float,
    centre_cov: float,
    has_centre: bool,
    out_mean: FloatArray,
    out_cov: FloatArray,
) -> bool:
    """Sigma-point prediction of the adaptive-turn model over all 8 components."""
    factor = np.zeros((8, 8))
    if not cholesky(cov, 8, factor):
        return False
    first = 1 if has_centre else 0
    count = first + 16
    moved = np.empty((count, 8))
    mean_weights = np.full(count, side)
    cov_weights = np.full(count, side)
    point = np.empty(8)
    if has_centre:
        _turn_propagate(mean, f_omega, dt, moved[0])
        mean_weights[0], cov_weights[0] = centre_mean, centre_cov
    for i in range(8):
        for sign in range(2):
            for k in range(8):
                offset = spread * factor[k, i]
                point[k] = mean[k] + offset if sign == 0 else mean[k] + (-offset)
            _turn_propagate(point, f_omega, dt, moved[first + i + 8 * sign])
    for k in range(8):
        total = 0.0
        for p in range(count):
            total += mean_weights[p] * moved[p, k]
        out_mean[k] = total
    sin_sum, cos_sum = 0.0, 0.0
    for p in range(count):
        sin_sum += mean_weights[p] * math.sin(moved[p, _PHI])
        cos_sum += mean_weights[p] * math.cos(moved[p, _PHI])
    out_mean[_PHI] = math.atan2(sin_sum, cos_sum)
    for p in range(count):
        for k in range(8):
            moved[p, k] -= out_mean[k]
        moved[p, _PHI] = wrap(moved[p, _PHI])
    for i in range(8):
        for j in range(8):
            total = 0.0
            for p in range(count):
                total += cov_weights[p] * moved[p, i] * moved[p, j]
            out_cov[i, j] = total + noise[i, j]
    _symmetrize(out_cov, 8)
    return True
