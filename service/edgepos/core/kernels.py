"""Compiled (numba) kernels of one IMM/2IMM bank epoch for RSU range/bearing + gyro measurements.

These are the same equations as the numpy reference (``core.imm``, ``core.filters``,
``core.updates``), written as plain loops over the padded 8-dim bank so that numba turns them into
machine code: on 8x8 matrices numpy spends its time in per-call overhead, not arithmetic. Every
kernel keeps the reference's numerics (symmetrised covariances, wrapped angles, circular means) and
returns a status instead of raising: ``OK``, or ``FAILED`` when a Cholesky factor does not exist or
a result is not finite. The caller (``core.compiled``) then re-runs the step on the numpy
reference, which repairs a nearly singular covariance or raises the typed ``NumericalError``: the
decisions about bad numbers are made in one place.

Conventions shared with the caller:
- filter kinds: ``EKF`` (analytic Jacobians) or ``SIGMA`` (a point set mean +- s L e_i with equal
  side weights, plus a centre point when ``has_centre``): CKF and UKF;
- motion kinds per model: ``LINEAR`` (padded F, Q of the interval) or ``TURN`` (the adaptive-turn
  model: the turn kinematics at the state's own omega, F_omega in the [phi, omega] block of F);
- measurement vector: [range_1, bearing_1, ..., range_K, bearing_K, yaw_rate_1, ..., yaw_rate_G].
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba
import numpy as np
import numpy.typing as npt

from edgepos.core.numerics import FloatArray

OK = 0
FAILED = 1

EKF = 0
SIGMA = 1

LINEAR = 0
TURN = 1

_TINY = 1e-300
_LOG_TWO_PI = math.log(2.0 * math.pi)
_TWO_PI = 2.0 * math.pi
_MIN_DISTANCE = 1e-3  # as core.measurements.rsu: Jacobians below 1 mm are taken at 1 mm
_SMALL_TURN = 1e-4  # as core.motion.turn
_XP, _XV, _XA, _YP, _YV, _YA, _PHI, _OMEGA = range(8)

#: The kernels' other array arguments (float64 states, covariances and scratch are FloatArray).
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

_Function = TypeVar("_Function", bound=Callable[..., Any])


def _jit(function: _Function) -> _Function:
    """njit with an on-disk cache (so no request pays compilation), or in memory when numba finds no
    writable cache directory (next to this file, NUMBA_CACHE_DIR or the user's cache directory):
    the service then compiles at warm-up instead.

    The kernels keep the GIL (no ``nogil``): each runs for microseconds, three times per epoch, and
    releasing the GIL around them let the service's event loop take it at every call, the filter
    thread then waiting up to a switch interval to get it back. Kept, a 20-epoch batch takes one
    hand-off instead of up to sixty; the event loop still preempts the filter thread every switch
    interval (5 ms). Measured: +8 % and +14 % closed-loop epochs/s of a 1-worker service, p99 at 100
    vehicles unchanged."""
    # numba ships no types: its dispatcher is called as the function it compiles, so it keeps that
    # function's signature for the type checker.
    try:
        return cast(_Function, numba.njit(cache=True, error_model="numpy")(function))
    except RuntimeError:  # "no locator available": nowhere to write the cache
        return cast(_Function, numba.njit(error_model="numpy")(function))


# -- small dense helpers -------------------------------------------------------------------------
@_jit
def wrap(angle: float) -> float:
    """Wrap to [-pi, pi), as ``core.numerics.wrap_angle`` (Python's floored modulo)."""
    return (angle + math.pi) % _TWO_PI - math.pi


@_jit
def cholesky(matrix: FloatArray, n: int, out: FloatArray) -> bool:
    """Lower Cholesky factor of matrix[:n, :n] into out[:n, :n]; False when not positive definite."""
    for j in range(n):
        total = matrix[j, j]
        for k in range(j):
            total -= out[j, k] * out[j, k]
        if not total > 0.0:  # also catches NaN
            return False
        diagonal = math.sqrt(total)
        out[j, j] = diagonal
        for i in range(j + 1, n):
            total = matrix[i, j]
            for k in range(j):
                total -= out[i, k] * out[j, k]
            out[i, j] = total / diagonal
        for i in range(j):
            out[i, j] = 0.0
    return True


@_jit
def _symmetrize(matrix: FloatArray, n: int) -> None:
    for i in range(n):
        for j in range(i + 1, n):
            value = 0.5 * (matrix[i, j] + matrix[j, i])
            matrix[i, j] = value
            matrix[j, i] = value


@_jit
def _all_finite(array: FloatArray) -> bool:
    total = 0.0
    for value in array.flat:
        total += value
    return math.isfinite(total)


@_jit
def _sinc(x: float) -> float:
    """sin(pi x) / (pi x), exactly 1 at 0."""
    if x == 0.0:
        return 1.0
    y = math.pi * x
    return math.sin(y) / y


# -- mixtures over the common components ---------------------------------------------------------
@_jit
def moment_match(
    weights: FloatArray,
    means: FloatArray,
    covs: FloatArray,
    common: IntArray,
    phi_slot: int,
    out_mean: FloatArray,
    out_cov: FloatArray,
) -> None:
    """Moment-matched Gaussian of a mixture over ``common`` (the heading at ``phi_slot``, -1 if none)."""
    count = means.shape[0]
    size = common.shape[0]
    for a in range(size):
        total = 0.0
        for b in range(count):
            total += weights[b] * means[b, common[a]]
        out_mean[a] = total
    if phi_slot >= 0:
        sin_sum, cos_sum = 0.0, 0.0
        for b in range(count):
            angle = means[b, common[phi_slot]]
            sin_sum += weights[b] * math.sin(angle)
            cos_sum += weights[b] * math.cos(angle)
        out_mean[phi_slot] = math.atan2(sin_sum, cos_sum)
    spread = np.empty((count, size))
    for b in range(count):
        for a in range(size):
            spread[b, a] = means[b, common[a]] - out_mean[a]
        if phi_slot >= 0:
            spread[b, phi_slot] = wrap(spread[b, phi_slot])
    for a in range(size):
        for c in range(size):
            total = 0.0
            for b in range(count):
                total += weights[b] * (covs[b, common[a], common[c]] + spread[b, a] * spread[b, c])
            out_cov[a, c] = total
    _symmetrize(out_cov, size)


@_jit
def _carry_extras(
    old_mean: FloatArray,
    old_cov: FloatArray,
    new_mean: FloatArray,
    new_cov: FloatArray,
    common: IntArray,
    extra: IntArray,
    phi_slot: int,
) -> bool:
    """A model's extra components follow their conditional given its re-mixed common block:
    B = P_ec P_cc^-1, x_e' = x_e + B (x_c' - x_c), P_ec' = B P_cc', P_ee' = P_ee - B P_ce + B P_cc' B^T."""
    nc, ne = common.shape[0], extra.shape[0]
    own_cc = np.empty((nc, nc))
    for a in range(nc):
        for c in range(nc):
            own_cc[a, c] = old_cov[common[a], common[c]]
    factor = np.zeros((nc, nc))
    if not cholesky(own_cc, nc, factor):
        return False
    regression = np.empty((ne, nc))  # rows: B = P_ec P_cc^-1, solved as P_cc B^T = P_ce
    column = np.empty(nc)
    for e in range(ne):
        for a in range(nc):
            total = old_cov[common[a], extra[e]]
            for k in range(a):
                total -= factor[a, k] * column[k]
            column[a] = total / factor[a, a]
        for a in range(nc - 1, -1, -1):
            total = column[a]
            for k in range(a + 1, nc):
                total -= factor[k, a] * column[k]
            column[a] = total / factor[a, a]
        for a in range(nc):
            regression[e, a] = column[a]
    shift = np.empty(nc)
    for a in range(nc):
        shift[a] = new_mean[common[a]] - old_mean[common[a]]
    if phi_slot >= 0:
        shift[phi_slot] = wrap(shift[phi_slot])
    for e in range(ne):
        total = 0.0
        for a in range(nc):
            total += regression[e, a] * shift[a]
        new_mean[extra[e]] = old_mean[extra[e]] + total
    new_mean[_PHI] = wrap(new_mean[_PHI])
    cross = np.empty((ne, nc))  # B P_cc'
    for e in range(ne):
        for c in range(nc):
            total = 0.0
            for a in range(nc):
                total += regression[e, a] * new_cov[common[a], common[c]]
            cross[e, c] = total
    for e in range(ne):
        for c in range(nc):
            new_cov[extra[e], common[c]] = cross[e, c]
            new_cov[common[c], extra[e]] = cross[e, c]
    for e in range(ne):
        for f in range(ne):
            total = old_cov[extra[e], extra[f]]
            for a in range(nc):
                total += cross[e, a] * regression[f, a] - regression[e, a] * old_cov[extra[f], common[a]]
            new_cov[extra[e], extra[f]] = total
    return True


@_jit
def mix(
    means: FloatArray,
    covs: FloatArray,
    probabilities: FloatArray,
    transition: FloatArray,
    active: BoolArray,
    common: IntArray,
    phi_slot: int,
    out_means: FloatArray,
    out_covs: FloatArray,
    out_predicted: FloatArray,
) -> int:
    """Interaction (eqs. 11-14): each model's mixed prior into out_means/out_covs, c_j into out_predicted."""
    count = means.shape[0]
    nc = common.shape[0]
    joint = np.empty((count, count))
    for i in range(count):
        for j in range(count):
            joint[i, j] = transition[i, j] * probabilities[i]
    predicted = np.empty(count)
    for j in range(count):
        total = 0.0
        for i in range(count):
            total += joint[i, j]
        if total < _TINY:  # no probability flows into j: it keeps its own estimate
            for i in range(count):
                joint[i, j] = 1.0 if i == j else 0.0
            total = _TINY
        predicted[j] = total
    weights = np.empty((count, count))  # weights[j, i] = mu_{i|j}
    for j in range(count):
        total = 0.0
        for i in range(count):
            total += joint[i, j]
        for i in range(count):
            weights[j, i] = joint[i, j] / total
    out_means[:, :] = means
    out_covs[:, :, :] = covs
    mixed_mean = np.empty(nc)
    mixed_cov = np.empty((nc, nc))
    for j in range(count):
        moment_match(weights[j], means, covs, common, phi_slot, mixed_mean, mixed_cov)
        for a in range(nc):
            out_means[j, common[a]] = mixed_mean[a]
            for c in range(nc):
                out_covs[j, common[a], common[c]] = mixed_cov[a, c]
    extra = np.empty(8, dtype=np.int64)
    for j in range(count):
        ne = 0
        for k in range(8):
            if active[j, k]:
                is_common = False
                for a in range(nc):
                    if common[a] == k:
                        is_common = True
                if not is_common:
                    extra[ne] = k
                    ne += 1
        if ne > 0 and not _carry_extras(
            means[j], covs[j], out_means[j], out_covs[j], common, extra[:ne], phi_slot
        ):
            return FAILED
    total = 0.0
    for j in range(count):
        _symmetrize(out_covs[j], 8)
        total += predicted[j]
    for j in range(count):
        out_predicted[j] = predicted[j] / total
    return OK


# -- prediction ----------------------------------------------------------------------------------
@_jit
def _linear_predict(
    transition: FloatArray,
    noise: FloatArray,
    mean: FloatArray,
    cov: FloatArray,
    out_mean: FloatArray,
    out_cov: FloatArray,
) -> None:
    """F m and F P F^T + Q on the padded 8x8 (zero rows stay zero)."""
    temp = np.empty((8, 8))
    for i in range(8):
        total = 0.0
        for k in range(8):
            total += transition[i, k] * mean[k]
        out_mean[i] = total
        for j in range(8):
            total = 0.0
            for k in range(8):
                total += transition[i, k] * cov[k, j]
            temp[i, j] = total
    for i in range(8):
        for j in range(8):
            total = noise[i, j]
            for k in range(8):
                total += temp[i, k] * transition[j, k]
            out_cov[i, j] = total


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


@_jit
def predict_bank(
    means: FloatArray,
    covs: FloatArray,
    kinds: IntArray,
    transitions: FloatArray,
    noises: FloatArray,
    dt: float,
    filter_kind: int,
    spreads: FloatArray,
    sides: FloatArray,
    centre_means: FloatArray,
    centre_covs: FloatArray,
    has_centre: bool,
    out_means: FloatArray,
    out_covs: FloatArray,
) -> int:
    """Every model's prediction over dt (``GaussianFilter.predict_bank``)."""
    count = means.shape[0]
    jacobian = np.empty((8, 8))
    scratch = np.empty(8)
    for b in range(count):
        if kinds[b] == LINEAR:
            _linear_predict(transitions[b], noises[b], means[b], covs[b], out_means[b], out_covs[b])
            _symmetrize(out_covs[b], 8)
        elif filter_kind == SIGMA:
            f_omega = transitions[b, 6:, 6:]
            if not _turn_predict_sigma(
                means[b],
                covs[b],
                f_omega,
                noises[b],
                dt,
                spreads[b],
                sides[b],
                centre_means[b],
                centre_covs[b],
                has_centre,
                out_means[b],
                out_covs[b],
            ):
                return FAILED
        else:
            f_omega = transitions[b, 6:, 6:]
            _turn_jacobian(means[b], f_omega, dt, jacobian)
            _turn_propagate(means[b], f_omega, dt, out_means[b])
            _linear_predict(jacobian, noises[b], means[b], covs[b], scratch, out_covs[b])
            _symmetrize(out_covs[b], 8)
        out_means[b, _PHI] = wrap(out_means[b, _PHI])
    if not (_all_finite(out_means) and _all_finite(out_covs)):
        return FAILED
    return OK


# -- measurements and the correction -------------------------------------------------------------
@_jit
def _measure(
    state: FloatArray, positions: FloatArray, rsus: IntArray, gyros: int, min_speed_sq: float, out: FloatArray
) -> None:
    """h(x): the ranges and bearings of ``rsus`` (indices into positions), then the yaw rate per gyro."""
    for r in range(rsus.shape[0]):
        dx = state[_XP] - positions[rsus[r], 0]
        dy = state[_YP] - positions[rsus[r], 1]
        out[2 * r] = math.hypot(dx, dy)
        out[2 * r + 1] = math.atan2(dy, dx)
    if gyros > 0:
        xv, xa, yv, ya = state[_XV], state[_XA], state[_YV], state[_YA]
        rate = (xv * ya - xa * yv) / max(xv * xv + yv * yv, min_speed_sq)
        for g in range(gyros):
            out[2 * rsus.shape[0] + g] = rate


@_jit
def _measure_jacobian(
    state: FloatArray, positions: FloatArray, rsus: IntArray, gyros: int, min_speed_sq: float, out: FloatArray
) -> None:
    """dh/dx at ``state`` (``RsuRangeBearing.jacobian`` and ``GyroYawRate.jacobian``)."""
    out[:, :] = 0.0
    for r in range(rsus.shape[0]):
        dx = state[_XP] - positions[rsus[r], 0]
        dy = state[_YP] - positions[rsus[r], 1]
        distance = max(math.hypot(dx, dy), _MIN_DISTANCE)
        out[2 * r, _XP] = dx / distance
        out[2 * r, _YP] = dy / distance
        out[2 * r + 1, _XP] = -dy / distance**2
        out[2 * r + 1, _YP] = dx / distance**2
    if gyros > 0:
        xv, xa, yv, ya = state[_XV], state[_XA], state[_YV], state[_YA]
        raw_speed_sq = xv * xv + yv * yv
        moving = raw_speed_sq > min_speed_sq
        speed_sq = raw_speed_sq if moving else min_speed_sq
        cross_term = 2.0 * (xv * ya - xa * yv) / speed_sq**2 if moving else 0.0
        for g in range(gyros):
            row = 2 * rsus.shape[0] + g
            out[row, _XA] = -yv / speed_sq
            out[row, _YA] = xv / speed_sq
            out[row, _XV] = ya / speed_sq - xv * cross_term
            out[row, _YV] = -xa / speed_sq - yv * cross_term


@_jit
def _moments(
    mean: FloatArray,
    cov: FloatArray,
    active_row: BoolArray,
    positions: FloatArray,
    rsus: IntArray,
    gyros: int,
    min_speed_sq: float,
    variances: FloatArray,
    filter_kind: int,
    spread: float,
    side: float,
    centre_mean: float,
    centre_cov: float,
    has_centre: bool,
    predicted: FloatArray,
    innovation_cov: FloatArray,
    cross_cov: FloatArray,
) -> bool:
    """Predicted measurement, S (with R, symmetrised) and C for one model (``measurement_moments``)."""
    size = predicted.shape[0]
    angle_rows = 2 * rsus.shape[0]
    if filter_kind == EKF:
        _measure(mean, positions, rsus, gyros, min_speed_sq, predicted)
        jacobian = np.empty((size, 8))
        _measure_jacobian(mean, positions, rsus, gyros, min_speed_sq, jacobian)
        for r in range(size):
            for k in range(8):
                if not active_row[k]:
                    jacobian[r, k] = 0.0
        for i in range(8):
            for r in range(size):
                total = 0.0
                for k in range(8):
                    total += cov[i, k] * jacobian[r, k]
                cross_cov[i, r] = total
        for r in range(size):
            for s in range(size):
                total = 0.0
                for k in range(8):
                    total += jacobian[r, k] * cross_cov[k, s]
                innovation_cov[r, s] = total
    else:
        padded = cov.copy()
        for k in range(8):
            if not active_row[k]:
                padded[k, k] += 1.0
        factor = np.zeros((8, 8))
        if not cholesky(padded, 8, factor):
            return False
        first = 1 if has_centre else 0
        count = first + 16
        offsets = np.zeros((count, 8))
        weights = np.zeros(count)
        cov_weights = np.zeros(count)
        if has_centre:
            weights[0], cov_weights[0] = centre_mean, centre_cov
        for i in range(8):
            if active_row[i]:
                weights[first + i] = side
                weights[first + 8 + i] = side
                cov_weights[first + i] = side
                cov_weights[first + 8 + i] = side
                for k in range(8):
                    offsets[first + i, k] = spread * factor[k, i]
                    offsets[first + 8 + i, k] = -(spread * factor[k, i])
        z = np.empty((count, size))
        point = np.empty(8)
        for p in range(count):
            for k in range(8):
                point[k] = mean[k] + offsets[p, k]
            _measure(point, positions, rsus, gyros, min_speed_sq, z[p])
        for r in range(size):
            total = 0.0
            for p in range(count):
                total += weights[p] * z[p, r]
            predicted[r] = total
        for r in range(1, angle_rows, 2):
            sin_sum, cos_sum = 0.0, 0.0
            for p in range(count):
                sin_sum += weights[p] * math.sin(z[p, r])
                cos_sum += weights[p] * math.cos(z[p, r])
            predicted[r] = math.atan2(sin_sum, cos_sum)
        for p in range(count):
            for r in range(size):
                z[p, r] -= predicted[r]
            for r in range(1, angle_rows, 2):
                z[p, r] = wrap(z[p, r])
        for r in range(size):
            for s in range(r, size):
                total = 0.0
                for p in range(count):
                    total += z[p, r] * cov_weights[p] * z[p, s]
                innovation_cov[r, s] = total
                innovation_cov[s, r] = total
        for k in range(8):
            for r in range(size):
                total = 0.0
                for p in range(count):
                    total += offsets[p, k] * (z[p, r] * cov_weights[p])
                cross_cov[k, r] = total
    for r in range(size):
        innovation_cov[r, r] += variances[r]
    _symmetrize(innovation_cov, size)
    return True


@_jit
def _correct_one(
    mean: FloatArray,
    cov: FloatArray,
    active_row: BoolArray,
    positions: FloatArray,
    rsus: IntArray,
    observed: FloatArray,
    gyros: int,
    min_speed_sq: float,
    variances: FloatArray,
    filter_kind: int,
    spread: float,
    side: float,
    centre_mean: float,
    centre_cov: float,
    has_centre: bool,
    out_mean: FloatArray,
    out_cov: FloatArray,
    stats: FloatArray,
) -> bool:
    """One model's Kalman correction through the Cholesky factor of S (``kalman_correct``);
    stats receives (NIS, log-likelihood)."""
    size = observed.shape[0]
    predicted = np.empty(size)
    innovation_cov = np.empty((size, size))
    cross_cov = np.empty((8, size))
    if not _moments(
        mean,
        cov,
        active_row,
        positions,
        rsus,
        gyros,
        min_speed_sq,
        variances,
        filter_kind,
        spread,
        side,
        centre_mean,
        centre_cov,
        has_centre,
        predicted,
        innovation_cov,
        cross_cov,
    ):
        return False
    factor = np.zeros((size, size))
    if not cholesky(innovation_cov, size, factor):
        return False
    # Solve L [U | e] = [C^T | r] by forward substitution.
    rhs = np.empty((size, 9))
    for r in range(size):
        for k in range(8):
            rhs[r, k] = cross_cov[k, r]
        residual = observed[r] - predicted[r]
        if r < 2 * rsus.shape[0] and r % 2 == 1:
            residual = wrap(residual)
        rhs[r, 8] = residual
    for r in range(size):
        for c in range(9):
            total = rhs[r, c]
            for k in range(r):
                total -= factor[r, k] * rhs[k, c]
            rhs[r, c] = total / factor[r, r]
    nis = 0.0
    log_det = 0.0
    for r in range(size):
        nis += rhs[r, 8] * rhs[r, 8]
        log_det += math.log(factor[r, r])
    for k in range(8):
        total = 0.0
        for r in range(size):
            total += rhs[r, k] * rhs[r, 8]
        out_mean[k] = mean[k] + total
    out_mean[_PHI] = wrap(out_mean[_PHI])
    for i in range(8):
        for j in range(8):
            total = 0.0
            for r in range(size):
                total += rhs[r, i] * rhs[r, j]
            out_cov[i, j] = cov[i, j] - total
    _symmetrize(out_cov, 8)
    stats[0] = nis
    stats[1] = -0.5 * (nis + 2.0 * log_det + size * _LOG_TWO_PI)
    return True


@_jit
def correct_bank(
    means: FloatArray,
    covs: FloatArray,
    active: BoolArray,
    positions: FloatArray,
    observed_rsus: FloatArray,
    yaw_rates: FloatArray,
    range_variances: FloatArray,
    bearing_variances: FloatArray,
    gyro_variance: float,
    min_speed_sq: float,
    averaged: bool,
    filter_kind: int,
    spreads: FloatArray,
    sides: FloatArray,
    centre_means: FloatArray,
    centre_covs: FloatArray,
    has_centre: bool,
    out_means: FloatArray,
    out_covs: FloatArray,
    out_nis: FloatArray,
    out_log_likelihood: FloatArray,
) -> int:
    """Every model's update with K RSUs (positions (K, 2), observed (K, 2) range and bearing) and G gyro
    readings: one joint update, or with ``averaged`` one per RSU (each with the gyros), averaged
    (``core.updates``)."""
    count = means.shape[0]
    rsu_count = positions.shape[0]
    gyros = yaw_rates.shape[0]
    parts = rsu_count if averaged and rsu_count > 1 else 1
    per_part = rsu_count if parts == 1 else 1
    size = 2 * per_part + gyros
    rsus = np.empty(per_part, dtype=np.int64)
    observed = np.empty(size)
    variances = np.empty(size)
    part_mean = np.empty(8)
    part_cov = np.empty((8, 8))
    stats = np.empty(2)
    sin_sum = np.empty(count)
    cos_sum = np.empty(count)
    out_means[:, :] = 0.0
    out_covs[:, :, :] = 0.0
    out_nis[:] = 0.0
    out_log_likelihood[:] = 0.0
    sin_sum[:] = 0.0
    cos_sum[:] = 0.0
    for part in range(parts):
        for r in range(per_part):
            rsu = r if parts == 1 else part
            rsus[r] = rsu
            observed[2 * r] = observed_rsus[rsu, 0]
            observed[2 * r + 1] = observed_rsus[rsu, 1]
            variances[2 * r] = range_variances[rsu]
            variances[2 * r + 1] = bearing_variances[rsu]
        for g in range(gyros):
            observed[2 * per_part + g] = yaw_rates[g]
            variances[2 * per_part + g] = gyro_variance
        for b in range(count):
            if not _correct_one(
                means[b],
                covs[b],
                active[b],
                positions,
                rsus,
                observed,
                gyros,
                min_speed_sq,
                variances,
                filter_kind,
                spreads[b],
                sides[b],
                centre_means[b],
                centre_covs[b],
                has_centre,
                part_mean,
                part_cov,
                stats,
            ):
                return FAILED
            if parts == 1:
                out_means[b, :] = part_mean
                out_covs[b, :, :] = part_cov
                out_nis[b] = stats[0]
                out_log_likelihood[b] = stats[1]
            else:
                for k in range(8):
                    out_means[b, k] += part_mean[k]
                    for j in range(8):
                        out_covs[b, k, j] += part_cov[k, j]
                sin_sum[b] += math.sin(part_mean[_PHI])
                cos_sum[b] += math.cos(part_mean[_PHI])
                out_nis[b] += stats[0]
                out_log_likelihood[b] += stats[1]
    if parts > 1:
        for b in range(count):
            for k in range(8):
                out_means[b, k] /= parts
                for j in range(8):
                    out_covs[b, k, j] /= parts
            heading = math.atan2(sin_sum[b] / parts, cos_sum[b] / parts)
            out_means[b, _PHI] = heading if active[b, _PHI] else 0.0
            out_nis[b] /= parts
            out_log_likelihood[b] /= parts
    if not (_all_finite(out_means) and _all_finite(out_covs) and _all_finite(out_log_likelihood)):
        return FAILED
    return OK


# -- model probabilities -------------------------------------------------------------------------
@_jit
def _softmax_into(log_weights: FloatArray, out: FloatArray) -> None:
    top = log_weights.max()
    total = 0.0
    for i in range(log_weights.shape[0]):
        out[i] = math.exp(log_weights[i] - top)
        total += out[i]
    for i in range(log_weights.shape[0]):
        out[i] /= total


@_jit
def model_probabilities(
    log_likelihoods: FloatArray, predicted: FloatArray, priority: IntArray, others: IntArray, out: FloatArray
) -> None:
    """IMM (softmax of log c_j + log L_j) or, with ``others``, the 2IMM eqs. 30 and 33-38."""
    count = log_likelihoods.shape[0]
    log_predicted = np.empty(count)
    for j in range(count):
        log_predicted[j] = math.log(max(predicted[j], _TINY))
    if others.shape[0] == 0:
        _softmax_into(log_likelihoods + log_predicted, out)
        return
    first_count = priority.shape[0]
    first = np.empty(first_count)
    best_first = -np.inf
    first_mass = 0.0
    for a in range(first_count):
        first[a] = log_likelihoods[priority[a]] + log_predicted[priority[a]]
        best_first = max(best_first, log_likelihoods[priority[a]])
        first_mass += math.exp(log_predicted[priority[a]])
    first_probs = np.empty(first_count)
    _softmax_into(first, first_probs)
    second = np.empty(1 + others.shape[0])
    second[0] = best_first + math.log(first_mass)
    for a in range(others.shape[0]):
        second[1 + a] = log_likelihoods[others[a]] + log_predicted[others[a]]
    second_probs = np.empty(second.shape[0])
    _softmax_into(second, second_probs)
    for a in range(first_count):
        out[priority[a]] = first_probs[a] * second_probs[0]
    for a in range(others.shape[0]):
        out[others[a]] = second_probs[1 + a]


# -- the gate ------------------------------------------------------------------------------------
@_jit
def gate_distances(
    mean: FloatArray,
    cov: FloatArray,
    common: IntArray,
    positions: FloatArray,
    observed_rsus: FloatArray,
    yaw_rates: FloatArray,
    range_variances: FloatArray,
    bearing_variances: FloatArray,
    gyro_variance: float,
    min_speed_sq: float,
    rsu_out: FloatArray,
    gyro_out: FloatArray,
) -> None:
    """Squared Mahalanobis distance of each RSU pair (2 dof) and gyro reading (1 dof) against a
    Gaussian over ``common`` (``mean`` is the full 8-vector, zero elsewhere), linearised at its mean."""
    rsu_count = positions.shape[0]
    gyros = yaw_rates.shape[0]
    size = 2 * rsu_count + gyros
    rsus = np.arange(rsu_count)
    predicted = np.empty(size)
    jacobian = np.empty((size, 8))
    _measure(mean, positions, rsus, gyros, min_speed_sq, predicted)
    _measure_jacobian(mean, positions, rsus, gyros, min_speed_sq, jacobian)
    nc = common.shape[0]
    projected = np.empty((size, nc))  # H P over the common components
    for r in range(size):
        for c in range(nc):
            total = 0.0
            for a in range(nc):
                total += jacobian[r, common[a]] * cov[a, c]
            projected[r, c] = total
    for r in range(rsu_count):
        block = np.empty((2, 2))
        for i in range(2):
            for j in range(2):
                total = 0.0
                for c in range(nc):
                    total += projected[2 * r + i, c] * jacobian[2 * r + j, common[c]]
                block[i, j] = total
        s11 = block[0, 0] + range_variances[r]
        s22 = block[1, 1] + bearing_variances[r]
        s12 = block[0, 1]
        r1 = observed_rsus[r, 0] - predicted[2 * r]
        r2 = wrap(observed_rsus[r, 1] - predicted[2 * r + 1])
        rsu_out[r] = (s22 * r1 * r1 - 2.0 * s12 * r1 * r2 + s11 * r2 * r2) / (s11 * s22 - s12 * s12)
    for g in range(gyros):
        row = 2 * rsu_count + g
        total = 0.0
        for c in range(nc):
            total += projected[row, c] * jacobian[row, common[c]]
        residual = yaw_rates[g] - predicted[row]
        gyro_out[g] = residual * residual / (total + gyro_variance)


# -- the two entry points of an epoch ------------------------------------------------------------
@_jit
def predict_step(
    means: FloatArray,
    covs: FloatArray,
    probabilities: FloatArray,
    transition: FloatArray,
    active: BoolArray,
    common: IntArray,
    phi_slot: int,
    dt: float,
    kinds: IntArray,
    transitions: FloatArray,
    noises: FloatArray,
    filter_kind: int,
    spreads: FloatArray,
    sides: FloatArray,
    centre_means: FloatArray,
    centre_covs: FloatArray,
    has_centre: bool,
) -> tuple[int, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Interaction, every model's prediction over dt (none when dt is 0) and the fused prior.

    Returns (status, means, covs, predicted probabilities c_j, fused mean, fused cov over common)."""
    count = means.shape[0]
    nc = common.shape[0]
    mixed_means = np.empty((count, 8))
    mixed_covs = np.empty((count, 8, 8))
    predicted = np.empty(count)
    out_means = np.empty((count, 8))
    out_covs = np.empty((count, 8, 8))
    fused_mean = np.empty(nc)
    fused_cov = np.empty((nc, nc))
    status = mix(
        means, covs, probabilities, transition, active, common, phi_slot, mixed_means, mixed_covs, predicted
    )
    if status == OK:
        if dt != 0.0:
            status = predict_bank(
                mixed_means,
                mixed_covs,
                kinds,
                transitions,
                noises,
                dt,
                filter_kind,
                spreads,
                sides,
                centre_means,
                centre_covs,
                has_centre,
                out_means,
                out_covs,
            )
        else:
            out_means[:, :] = mixed_means
            out_covs[:, :, :] = mixed_covs
    if status == OK:
        moment_match(predicted, out_means, out_covs, common, phi_slot, fused_mean, fused_cov)
    return status, out_means, out_covs, predicted, fused_mean, fused_cov


@_jit
def correct_step(
    means: FloatArray,
    covs: FloatArray,
    predicted: FloatArray,
    active: BoolArray,
    common: IntArray,
    phi_slot: int,
    priority: IntArray,
    others: IntArray,
    positions: FloatArray,
    observed_rsus: FloatArray,
    yaw_rates: FloatArray,
    range_variances: FloatArray,
    bearing_variances: FloatArray,
    gyro_variance: float,
    min_speed_sq: float,
    averaged: bool,
    filter_kind: int,
    spreads: FloatArray,
    sides: FloatArray,
    centre_means: FloatArray,
    centre_covs: FloatArray,
    has_centre: bool,
) -> tuple[int, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Every model's update, the model probabilities (IMM or 2IMM) and the fused posterior.

    Returns (status, means, covs, probabilities, log-likelihoods, NIS, fused mean, fused cov)."""
    count = means.shape[0]
    nc = common.shape[0]
    out_means = np.empty((count, 8))
    out_covs = np.empty((count, 8, 8))
    nis = np.empty(count)
    log_likelihoods = np.empty(count)
    probabilities = np.empty(count)
    fused_mean = np.empty(nc)
    fused_cov = np.empty((nc, nc))
    status = correct_bank(
        means,
        covs,
        active,
        positions,
        observed_rsus,
        yaw_rates,
        range_variances,
        bearing_variances,
        gyro_variance,
        min_speed_sq,
        averaged,
        filter_kind,
        spreads,
        sides,
        centre_means,
        centre_covs,
        has_centre,
        out_means,
        out_covs,
        nis,
        log_likelihoods,
    )
    if status == OK:
        model_probabilities(log_likelihoods, predicted, priority, others, probabilities)
        moment_match(probabilities, out_means, out_covs, common, phi_slot, fused_mean, fused_cov)
    return status, out_means, out_covs, probabilities, log_likelihoods, nis, fused_mean, fused_cov
