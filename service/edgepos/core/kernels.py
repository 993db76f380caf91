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
- measurement vector: [range_1, bearing_1, ..., range_K, bearing_K, yaw_rate_1, ..., yaw_rate_G];
- ``weights`` (4, B) of the entry points: per model the sigma-point spread s, the side points'
  weight, and the centre point's mean and covariance weights (one argument: each costs a call
  about 0.1 us to type).

This module holds the mixing, the prediction, the gate and the epoch's entry points
(``predict_epoch`` and ``predict_step``, ``correct_step``); ``kernels_turn`` the adaptive-turn model's
prediction; ``kernels_correct`` the correction and the model probabilities;
``kernels_base`` the codes above, the decorator and the small dense helpers all of them use.
"""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.kernels_base import (
    _PHI,
    _TINY,
    FAILED,
    LINEAR,
    OK,
    SIGMA,
    BoolArray,
    IntArray,
    _all_finite,
    _jit,
    _symmetrize,
    cholesky,
    cholesky_solve,
    wrap,
)
from edgepos.core.kernels_correct import (
    _measure,
    _measure_jacobian,
    correct_bank,
    model_probabilities,
)
from edgepos.core.kernels_motion import bank_step_matrices
from edgepos.core.kernels_turn import _turn_jacobian, _turn_predict_sigma, _turn_propagate
from edgepos.core.numerics import FloatArray


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
    work = np.empty(nc)
    for e in range(ne):
        for a in range(nc):
            column[a] = old_cov[common[a], extra[e]]
        cholesky_solve(factor, nc, column, work, regression[e])
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
# Each writes its results into one flat array the caller allocates per call (fresh memory: a
# Prediction or StepResult stays valid however long it is kept): a compiled function returning
# arrays boxes each one, about 0.7 us apiece through numba's unpickling of the array type, twelve
# per epoch. The layout: means (B, 8), covs (B, 8, 8), probabilities (B,), fused mean (nc,), fused
# cov (nc, nc); a correction then also log-likelihoods (B,) and NIS (B,).
def prediction_size(count: int, nc: int) -> int:
    """Length of ``predict_step``'s output array for ``count`` models and ``nc`` common components."""
    return count * (1 + 8 + 64) + nc * (1 + nc)


def correction_size(count: int, nc: int) -> int:
    """Length of ``correct_step``'s output array."""
    return count * (1 + 8 + 64) + nc * (1 + nc) + 2 * count


def prediction_views(
    out: FloatArray, count: int, nc: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """means, covs, probabilities, fused mean and fused cov: views of an output array (either kind)."""
    a, b, c = 8 * count, 72 * count, 73 * count
    return (
        out[:a].reshape(count, 8),
        out[a:b].reshape(count, 8, 8),
        out[b:c],
        out[c : c + nc],
        out[c + nc : c + nc * (1 + nc)].reshape(nc, nc),
    )


_prediction_parts = _jit(prediction_views)


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
    weights: FloatArray,
    has_centre: bool,
    out: FloatArray,
) -> int:
    """Interaction, every model's prediction over dt (none when dt is 0) and the fused prior.

    Writes into ``out`` (flat, ``prediction_size`` long) the means, covs, predicted probabilities c_j,
    fused mean and fused cov over common, in that order (``prediction_views`` gives them back as
    arrays): the caller allocates one array, where returning five cost a boxing each. Returns the status."""
    count = means.shape[0]
    nc = common.shape[0]
    mixed_means = np.empty((count, 8))
    mixed_covs = np.empty((count, 8, 8))
    out_means, out_covs, predicted, fused_mean, fused_cov = _prediction_parts(out, count, nc)
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
                weights[0],
                weights[1],
                weights[2],
                weights[3],
                has_centre,
                out_means,
                out_covs,
            )
        else:
            out_means[:, :] = mixed_means
            out_covs[:, :, :] = mixed_covs
    if status == OK:
        moment_match(predicted, out_means, out_covs, common, phi_slot, fused_mean, fused_cov)
    return status


@_jit
def predict_epoch(
    means: FloatArray,
    covs: FloatArray,
    probabilities: FloatArray,
    transition: FloatArray,
    active: BoolArray,
    common: IntArray,
    phi_slot: int,
    dt: float,
    step_dt: float,
    motion_kinds: IntArray,
    motion_params: FloatArray,
    kinds: IntArray,
    filter_kind: int,
    weights: FloatArray,
    has_centre: bool,
    out: FloatArray,
) -> int:
    """``predict_step`` with the models' F and Q over ``step_dt`` (dt as the reference rounds it for
    discretisation) from ``kernels_motion.bank_step_matrices`` in the same call: with jittered
    timestamps every interval is new, and a separate call (two arrays, a cache lookup) cost more than
    the matrices."""
    count = means.shape[0]
    transitions = np.zeros((count, 8, 8))
    noises = np.zeros((count, 8, 8))
    if dt != 0.0:
        bank_step_matrices(motion_kinds, motion_params, step_dt, transitions, noises)
    return predict_step(
        means,
        covs,
        probabilities,
        transition,
        active,
        common,
        phi_slot,
        dt,
        kinds,
        transitions,
        noises,
        filter_kind,
        weights,
        has_centre,
        out,
    )


@_jit
def correct_step(
    prediction: FloatArray,
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
    weights: FloatArray,
    has_centre: bool,
    out: FloatArray,
) -> int:
    """Every model's update, the model probabilities (IMM or 2IMM) and the fused posterior, from
    ``prediction``, the output array of ``predict_step``.

    Writes into ``out`` (flat, ``correction_size`` long) the means, covs, probabilities, fused mean
    and fused cov as ``predict_step`` lays them out, then the log-likelihoods and NIS. Returns the
    status."""
    count = active.shape[0]
    nc = common.shape[0]
    means, covs, predicted, _, _ = _prediction_parts(prediction, count, nc)
    out_means, out_covs, probabilities, fused_mean, fused_cov = _prediction_parts(out, count, nc)
    tail = 73 * count + nc * (1 + nc)  # prediction_size
    log_likelihoods = out[tail : tail + count]
    nis = out[tail + count : tail + 2 * count]
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
        weights[0],
        weights[1],
        weights[2],
        weights[3],
        has_centre,
        out_means,
        out_covs,
        nis,
        log_likelihoods,
    )
    if status == OK:
        model_probabilities(log_likelihoods, predicted, priority, others, probabilities)
        moment_match(probabilities, out_means, out_covs, common, phi_slot, fused_mean, fused_cov)
    return status


@_jit
def gate_prediction(
    prediction: FloatArray,
    count: int,
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
    """``gate_distances`` against the fused prior of ``prediction`` (``predict_step``'s output array)."""
    nc = common.shape[0]
    _, _, _, fused_mean, fused_cov = _prediction_parts(prediction, count, nc)
    mean = np.zeros(8)
    for a in range(nc):
        mean[common[a]] = fused_mean[a]
    gate_distances(
        mean,
        fused_cov,
        common,
        positions,
        observed_rsus,
        yaw_rates,
        range_variances,
        bearing_variances,
        gyro_variance,
        min_speed_sq,
        rsu_out,
        gyro_out,
    )
