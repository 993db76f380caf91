"""Compiled kernels of the bank's correction: the RSU range/bearing and gyro measurement functions,
one model's joint update (EKF or sigma-point), the whole bank's, and the model probabilities from
the innovations' likelihoods. See ``core.kernels`` for the conventions."""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.kernels_base import (
    _LOG_TWO_PI,
    _MIN_DISTANCE,
    _PHI,
    _TINY,
    _XA,
    _XP,
    _XV,
    _YA,
    _YP,
    _YV,
    EKF,
    FAILED,
    OK,
    BoolArray,
    IntArray,
    _all_finite,
    _jit,
    _symmetrize,
    cholesky,
    wrap,
)
from edgepos.core.numerics import FloatArray


# -- measurements and the correction -------------------------------------------------------------
@_jit
def _wrap_near(angle: float) -> float:
    """``wrap`` for an angle that is nearly always in range already (a sigma point's bearing about the
    predicted one): returned as it is then, which skips the floored modulo (a third of the points' cost
    besides atan2) and its rounding of angle + pi - pi, an ulp of pi at most."""
    if -math.pi <= angle < math.pi:
        return angle
    return wrap(angle)


@_jit
def _measure(
    state: FloatArray, positions: FloatArray, rsus: IntArray, gyros: int, min_speed_sq: float, out: FloatArray
) -> None:
    """h(x): the ranges and bearings of ``rsus`` (indices into positions), then the yaw rate per gyro."""
    for r in range(rsus.shape[0]):
        dx = state[_XP] - positions[rsus[r], 0]
        dy = state[_YP] - positions[rsus[r], 1]
        out[2 * r] = math.sqrt(dx * dx + dy * dy)  # hypot's care for overflow costs 5x, and ranges are metres
        out[2 * r + 1] = math.atan2(dy, dx)
    _measure_gyros(state, gyros, min_speed_sq, 2 * rsus.shape[0], out)


@_jit
def _measure_rsus(state: FloatArray, positions: FloatArray, rsus: IntArray, out: FloatArray) -> None:
    """Per RSU of ``rsus``: the range and bearing ``_measure`` gives, then the unit vector from the RSU
    (zero at zero range), as the sigma-point moments use it."""
    for r in range(rsus.shape[0]):
        dx = state[_XP] - positions[rsus[r], 0]
        dy = state[_YP] - positions[rsus[r], 1]
        distance = math.sqrt(dx * dx + dy * dy)
        out[r, 0] = distance
        out[r, 1] = math.atan2(dy, dx)
        if distance > 0.0:
            inverse = 1.0 / distance
            out[r, 2] = dx * inverse
            out[r, 3] = dy * inverse
        else:
            out[r, 2] = 0.0
            out[r, 3] = 0.0


@_jit
def _measure_gyros(state: FloatArray, gyros: int, min_speed_sq: float, first: int, out: FloatArray) -> None:
    """The yaw-rate rows of ``_measure``, written from ``out[first]`` on."""
    if gyros > 0:
        xv, xa, yv, ya = state[_XV], state[_XA], state[_YV], state[_YA]
        rate = (xv * ya - xa * yv) / max(xv * xv + yv * yv, min_speed_sq)
        for g in range(gyros):
            out[first + g] = rate


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
        # Only the active components' points: an inactive one's would sit at the mean with weight 0 and
        # add exact zeros to every sum below (a model over 6 of the 8 components skips 4 of 16 points).
        first = 1 if has_centre else 0
        dims = 0
        for i in range(8):
            if active_row[i]:
                dims += 1
        count = first + 2 * dims
        offsets = np.zeros((count, 8))
        weights = np.zeros(count)
        cov_weights = np.zeros(count)
        if has_centre:
            weights[0], cov_weights[0] = centre_mean, centre_cov
        slot = 0
        for i in range(8):
            if active_row[i]:
                weights[first + slot] = side
                weights[first + dims + slot] = side
                cov_weights[first + slot] = side
                cov_weights[first + dims + slot] = side
                for k in range(8):
                    offsets[first + slot, k] = spread * factor[k, i]
                    offsets[first + dims + slot, k] = -(spread * factor[k, i])
                slot += 1
        z = np.empty((count, size))
        point = np.empty(8)
        sin_sums = np.zeros(rsus.shape[0])
        cos_sums = np.zeros(rsus.shape[0])
        # A point whose offset leaves x and y as they are (the factor's columns past y's: half of an
        # 8-component model's points) sees the RSUs exactly as the mean does: their ranges, bearings and
        # unit vectors are measured once, at the mean, and copied (the same numbers, without the atan2s).
        at_mean = np.empty((rsus.shape[0], 4))  # range, bearing, unit vector x, y
        at_mean_measured = False
        for p in range(count):
            for k in range(8):
                point[k] = mean[k] + offsets[p, k]
            if offsets[p, _XP] == 0.0 and offsets[p, _YP] == 0.0:
                if not at_mean_measured:
                    _measure_rsus(point, positions, rsus, at_mean)
                    at_mean_measured = True
                for j in range(rsus.shape[0]):
                    z[p, 2 * j] = at_mean[j, 0]
                    z[p, 2 * j + 1] = at_mean[j, 1]
                _measure_gyros(point, gyros, min_speed_sq, 2 * rsus.shape[0], z[p])
                for j in range(rsus.shape[0]):
                    if at_mean[j, 0] > 0.0:
                        cos_sums[j] += weights[p] * at_mean[j, 2]
                        sin_sums[j] += weights[p] * at_mean[j, 3]
                    else:
                        cos_sums[j] += weights[p]
                continue
            _measure(point, positions, rsus, gyros, min_speed_sq, z[p])
            for j in range(rsus.shape[0]):
                distance = z[p, 2 * j]
                if distance > 0.0:
                    inverse = 1.0 / distance
                    cos_sums[j] += weights[p] * ((point[_XP] - positions[rsus[j], 0]) * inverse)
                    sin_sums[j] += weights[p] * ((point[_YP] - positions[rsus[j], 1]) * inverse)
                else:
                    cos_sums[j] += weights[p]
        # The sums below run point by point in the outer loop: each element still adds its terms in
        # point order (the same numbers to the last bit as a sum per element), but the inner loops'
        # additions are independent of one another, where a sum per element waits on its previous add.
        predicted[:size] = 0.0
        for p in range(count):
            weight = weights[p]
            for r in range(size):
                predicted[r] += weight * z[p, r]
        for j in range(rsus.shape[0]):
            predicted[2 * j + 1] = math.atan2(sin_sums[j], cos_sums[j])
        for p in range(count):
            for r in range(size):
                z[p, r] -= predicted[r]
            for r in range(1, angle_rows, 2):
                z[p, r] = _wrap_near(z[p, r])
        innovation_cov[:, :] = 0.0
        cross_cov[:, :] = 0.0
        weighted = np.empty(size)
        for p in range(count):
            for r in range(size):
                weighted[r] = z[p, r] * cov_weights[p]
            for r in range(size):
                for s in range(r, size):
                    innovation_cov[r, s] += weighted[r] * z[p, s]
            # A point's offset is zero in the components before its own (the factor is lower triangular)
            # and in those the model lacks: over half of them. Such a row adds exact zeros, which leave
            # every sum as it is (a sum from +0 never becomes -0), so it is skipped. Only a non-finite
            # residual would make those zeros NaN, and that fails the update either way.
            for k in range(8):
                offset = offsets[p, k]
                if offset != 0.0:
                    for r in range(size):
                        cross_cov[k, r] += offset * weighted[r]
        for r in range(size):
            for s in range(r + 1, size):
                innovation_cov[s, r] = innovation_cov[r, s]
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
    for r in range(size):  # row by row, each element's terms subtracted in the same order as a sum
        for k in range(r):
            coefficient = factor[r, k]
            for c in range(9):
                rhs[r, c] -= coefficient * rhs[k, c]
        diagonal = factor[r, r]
        for c in range(9):
            rhs[r, c] = rhs[r, c] / diagonal
    nis = 0.0
    log_det = 0.0
    for r in range(size):
        nis += rhs[r, 8] * rhs[r, 8]
        log_det += math.log(factor[r, r])
    gain = np.zeros(8)  # K r, and below K S K^T, each element summed over r in order
    reduction = np.zeros((8, 8))
    for r in range(size):
        for k in range(8):
            gain[k] += rhs[r, k] * rhs[r, 8]
        for i in range(8):
            left = rhs[r, i]
            if left != 0.0:  # zero in the components the model lacks: exact zeros skipped (see _moments)
                for j in range(8):
                    reduction[i, j] += left * rhs[r, j]
    for k in range(8):
        out_mean[k] = mean[k] + gain[k]
    out_mean[_PHI] = wrap(out_mean[_PHI])
    for i in range(8):
        for j in range(8):
            out_cov[i, j] = cov[i, j] - reduction[i, j]
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
