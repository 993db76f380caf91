"""The UPF's step with the GNSS-only motion model in compiled loops (numba), around the measurement's own
prediction function.

``upf.UnscentedParticleFilter.step`` with the shared linearisation is some 250 numpy calls on arrays of
(200, 15), (21, 15) and (10, 10): the time update of the particles' own covariance (sigma points through
``riss.GnssOnlyModel``), the particles' propagation, the shared UKF update, the proposal's draws and the
wrapping and completing of the angles after each. Each call costs microseconds of Python for a few
hundred floating-point operations. Here they are three kernels: the time update (:func:`time_update_kernel`:
the propagated cloud and the update's sigma points, in one array for the measurement function), then the
update and the draws (:func:`update_kernel`: the shared gain, posterior, proposal factor, the samples and
the kept particles and their deviations), then the existing weights kernel (``upf_kernel``). The
measurement's prediction (a Python callable: the compiled range kernel with the vehicle constraints) and
the numpy innovation score, moments and resampling stay as they are.

Same equations as the numpy step, which stays the reference (tests/core/test_core_upf_step_kernel.py holds
the two to 1e-9 on the same seeds) and runs with ``EDGEPOS_NUMBA=0``, with other motion models, and
wherever a kernel declines: a covariance or innovation covariance without a Cholesky factor, a non-finite
result, a cloud with no covariance of its own. The numpy step then repairs or raises, on the random
generator as it was before the kernels ran. Not bit for bit: the loops sum in index order where numpy's
matrix products sum by blocks, and their arctan2, exp and power are the C library's where numpy's are its
SIMD ones (sin, cos, sqrt and the angles' modulo agree exactly).
"""

from __future__ import annotations

import functools
import math
import time
from typing import NamedTuple

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.errors import NumericalError
from edgepos.core.kernels_base import FAILED, OK, _jit, cholesky, cholesky_solve
from edgepos.core.kernels_base import wrap as _wrap
from edgepos.core.measurements.gnss_kernel import anchor_array
from edgepos.core.motion.riss import (
    ANGLES,
    AZIMUTH,
    CLOCK,
    DIM,
    DRIFT,
    EAST,
    GYRO_BIAS,
    NORTH,
    PITCH,
    ROLL,
    UP,
    VE,
    VN,
    VU,
    WHEEL_SCALE,
    GnssOnlyModel,
)
from edgepos.core.numerics import FloatArray
from edgepos.core.particles.base import Cloud, Measurement, SigmaWeights
from edgepos.core.particles.upf_kernel import log_weights_kernel
from edgepos.gnss.geodesy import WGS84_A, WGS84_E2

POINT = 2
""":func:`time_update_kernel`'s status when the cloud has no covariance of its own (the numpy step's point
prior)."""
_CLOCKS = tuple(CLOCK.values())  # the constellations' clock biases, each integrating the drift
_MOVING_MPS = 0.5  # as GnssOnlyModel.complete


@_jit
def weighted_moments_into(
    points: FloatArray, weights: FloatArray, angles: np.ndarray, mean: FloatArray, cov: FloatArray
) -> None:
    """``base.weighted_moments`` of ``points`` (N, D) with ``weights`` (N,, summing to 1) into ``mean`` (D,)
    and ``cov`` (D, D, symmetrised): angles by their circular mean, their deviations wrapped."""
    count, dim = points.shape
    for c in range(dim):
        total = 0.0
        if angles[c]:
            sines = 0.0
            for i in range(count):
                sines += weights[i] * math.sin(points[i, c])
                total += weights[i] * math.cos(points[i, c])
            mean[c] = math.atan2(sines, total)
        else:
            for i in range(count):
                total += weights[i] * points[i, c]
            mean[c] = total
    offsets = np.empty((count, dim))
    scaled = np.empty((count, dim))
    for i in range(count):
        for c in range(dim):
            value = points[i, c] - mean[c]
            offsets[i, c] = _wrap(value) if angles[c] else value
            scaled[i, c] = offsets[i, c] * weights[i]
    product = np.dot(scaled.T, offsets)
    for a in range(dim):
        for b in range(dim):
            cov[a, b] = 0.5 * (product[a, b] + product[b, a])


@_jit
def _complete(row: FloatArray) -> None:
    """``GnssOnlyModel.complete`` of one state: azimuth and pitch of the velocity where it moves."""
    horizontal = math.hypot(row[VE], row[VN])
    if horizontal > _MOVING_MPS:
        row[AZIMUTH] = math.atan2(row[VE], row[VN])
        row[PITCH] = math.atan2(row[VU], horizontal)


@_jit
def _wrap_angles(row: FloatArray, angles: np.ndarray) -> None:
    """``base.wrap`` of one state's angle components (``angles`` a mask over the state)."""
    for c in range(row.shape[0]):
        if angles[c]:
            row[c] = _wrap(row[c])


@_jit
def _propagate(source: FloatArray, out: FloatArray, anchor: FloatArray, dt: float) -> None:
    """``GnssOnlyModel.propagate`` of one state (``anchor``: ``gnss_kernel.anchor_array``), completed."""
    lat0, height0, scale_north, scale_east = anchor[0], anchor[2], anchor[3], anchor[4]
    out[VE] = source[VE]
    out[VN] = source[VN]
    out[VU] = source[VU]
    lat_prev = lat0 + source[NORTH] / scale_north
    out[UP] = source[UP] + out[VU] * dt
    height = height0 + out[UP]
    s = math.sin(lat_prev)
    meridian = WGS84_A * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s * s) ** 1.5
    out[NORTH] = source[NORTH] + out[VN] * dt * scale_north / (meridian + height)
    lat = lat0 + out[NORTH] / scale_north
    s = math.sin(lat)
    normal = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)
    out[EAST] = source[EAST] + out[VE] * dt * scale_east / ((normal + height) * math.cos(lat))
    for c in _CLOCKS:
        out[c] = source[c] + source[DRIFT] * dt
    out[DRIFT] = source[DRIFT]
    out[PITCH] = source[PITCH]
    out[ROLL] = source[ROLL]
    out[AZIMUTH] = source[AZIMUTH]
    out[GYRO_BIAS] = source[GYRO_BIAS]
    out[WHEEL_SCALE] = source[WHEEL_SCALE]
    _complete(out)


@_jit
def _sigma_points(
    centre: FloatArray, chol: FloatArray, index: np.ndarray, scale: float, out: FloatArray
) -> None:
    """``base.sigma_points`` around one state: ``out`` (2k + 1, D) = the centre, then the centre plus and
    minus ``scale`` times each column of ``chol`` in the ``index`` components."""
    k = index.size
    for s in range(2 * k + 1):
        out[s, :] = centre
    for j in range(k):
        for a in range(k):
            step = scale * chol[a, j]
            out[1 + j, index[a]] += step
            out[1 + k + j, index[a]] -= step


@_jit
def time_update_kernel(
    particles: FloatArray,
    mean: FloatArray,
    cloud_cov: FloatArray,
    noise: FloatArray,
    index: np.ndarray,
    angles: np.ndarray,
    anchor: FloatArray,
    dt: float,
    scale: float,
    mean_weights: FloatArray,
    cov_weights: FloatArray,
    states: FloatArray,
    predicted_cov: FloatArray,
    chol: FloatArray,
) -> int:
    """``upf._own_prediction`` and the particles' propagation: ``predicted_cov`` (k, k) = the UKF time
    update of N(``mean``, ``cloud_cov``) over ``dt`` with process noise ``noise`` (D, D), ``chol`` its lower
    factor, ``states`` (N + 2k + 1, D) the particles propagated (wrapped, completed) and then the shared
    update's sigma points around the propagated mean. OK, FAILED (no Cholesky factor) or POINT (the cloud
    has no covariance of its own)."""
    count, dim = particles.shape
    k = index.size
    sigma = 2 * k + 1
    block = np.empty((k, k))
    spread = False
    for a in range(k):
        for b in range(k):
            block[a, b] = cloud_cov[index[a], index[b]]
            spread = spread or block[a, b] != 0.0
    if not spread:
        return POINT
    factor = np.empty((k, k))
    if not cholesky(block, k, factor):
        return FAILED
    points = np.empty((sigma, dim))
    _sigma_points(mean, factor, index, scale, points)
    moved = np.empty((sigma, dim))
    for s in range(sigma):
        _propagate(points[s], moved[s], anchor, dt)
    centre = np.empty(dim)
    for c in range(dim):
        total = 0.0
        if angles[c]:
            for s in range(sigma):
                total += mean_weights[s] * _wrap(moved[s, c] - moved[0, c])
            centre[c] = moved[0, c] + total
        else:
            for s in range(sigma):
                total += mean_weights[s] * moved[s, c]
            centre[c] = total
    _complete(centre)
    deviation = np.empty((sigma, k))
    for s in range(sigma):
        for a in range(k):
            value = moved[s, index[a]] - centre[index[a]]
            deviation[s, a] = _wrap(value) if angles[index[a]] else value
    for a in range(k):
        for b in range(k):
            total = noise[index[a], index[b]]
            for s in range(sigma):
                total += cov_weights[s] * deviation[s, a] * deviation[s, b]
            predicted_cov[a, b] = total
    if not cholesky(predicted_cov, k, chol):
        return FAILED
    reference = moved[0].copy()
    _wrap_angles(reference, angles)
    _complete(reference)
    for i in range(count):
        _propagate(particles[i], states[i], anchor, dt)
        _wrap_angles(states[i], angles)
        _complete(states[i])
    _sigma_points(reference, chol, index, scale, states[count:])
    return OK


@_jit
def update_kernel(
    predictions: FloatArray,
    states: FloatArray,
    index: np.ndarray,
    angles: np.ndarray,
    mean_weights: FloatArray,
    cov_weights: FloatArray,
    z: FloatArray,
    variances: FloatArray,
    predicted_cov: FloatArray,
    draws: FloatArray,
    root_fraction: float,
    posterior_cov: FloatArray,
    proposal_chol: FloatArray,
    z_hat: FloatArray,
    z_cov: FloatArray,
    sampled: FloatArray,
    particles: FloatArray,
    prior_deviation: FloatArray,
    proposal_deviation: FloatArray,
) -> int:
    """``base.shared_unscented_update`` and the UPF's draws from :func:`time_update_kernel`'s ``states``
    and their ``predictions`` (N + 2k + 1, m): the shared ``posterior_cov`` and its factor
    ``proposal_chol``, the particles' ``z_hat`` (N, m) and ``z_cov``; the samples (posterior + L ``draws``,
    wrapped and completed), the particles kept (posterior + ``root_fraction`` L draws) and the samples'
    deviations from the prior centres and from the posterior means (N, k). FAILED when the innovation
    covariance or the posterior covariance has no Cholesky factor or the update is not finite."""
    count, k = draws.shape
    sigma = 2 * k + 1
    m = z.size
    dim = states.shape[1]
    z_ref = np.zeros(m)
    for s in range(sigma):
        for j in range(m):
            z_ref[j] += mean_weights[s] * predictions[count + s, j]
    dz = np.empty((sigma, m))
    dx = np.empty((sigma, k))
    for s in range(sigma):
        for j in range(m):
            dz[s, j] = predictions[count + s, j] - z_ref[j]
        for a in range(k):
            value = states[count + s, index[a]] - states[count, index[a]]
            dx[s, a] = _wrap(value) if angles[index[a]] else value
    weighted = np.empty((sigma, m))
    weighted_dx = np.empty((sigma, k))
    for s in range(sigma):
        for j in range(m):
            weighted[s, j] = cov_weights[s] * dz[s, j]
        for a in range(k):
            weighted_dx[s, a] = cov_weights[s] * dx[s, a]
    z_cov[:, :] = np.dot(weighted.T, dz)
    for j in range(m):
        z_cov[j, j] += variances[j]
    cross = np.dot(weighted_dx.T, dz)
    root = np.empty((m, m))
    if not cholesky(z_cov, m, root):
        return FAILED
    gain = np.empty((k, m))  # cross z_cov^-1, row by row: z_cov g = cross[a] by the two triangular solves
    work = np.empty(m)
    for a in range(k):
        cholesky_solve(root, m, cross[a], work, gain[a])
    for a in range(k):
        for b in range(k):
            total = 0.0
            for j in range(m):
                total += gain[a, j] * cross[b, j]
            posterior_cov[a, b] = predicted_cov[a, b] - total
    for a in range(k):
        for b in range(a + 1, k):
            value = 0.5 * (posterior_cov[a, b] + posterior_cov[b, a])
            posterior_cov[a, b] = value
            posterior_cov[b, a] = value
    if not cholesky(posterior_cov, k, proposal_chol):  # also declines a non-finite covariance
        return FAILED
    innovation = np.empty((count, m))
    for i in range(count):
        for j in range(m):
            z_hat[i, j] = predictions[i, j] + (z_ref[j] - predictions[count, j])
            innovation[i, j] = z[j] - z_hat[i, j]
    step = np.dot(innovation, gain.T)  # (N, k)
    deviation_all = np.dot(draws, proposal_chol.T)  # (N, k)
    posterior = np.empty(dim)
    for i in range(count):
        posterior[:] = states[i]
        for a in range(k):
            posterior[index[a]] += step[i, a]
        for a in range(k):
            if angles[index[a]]:
                posterior[index[a]] = _wrap(posterior[index[a]])
        _complete(posterior)
        for c in range(dim):
            if not math.isfinite(posterior[c]):
                return FAILED
        deviation = deviation_all[i]
        sampled[i, :] = posterior
        particles[i, :] = posterior
        for a in range(k):
            sampled[i, index[a]] += deviation[a]
            particles[i, index[a]] += root_fraction * deviation[a]
        _wrap_angles(sampled[i], angles)
        _complete(sampled[i])
        _wrap_angles(particles[i], angles)
        _complete(particles[i])
        for a in range(k):
            c = index[a]
            prior = sampled[i, c] - states[i, c]
            proposal = sampled[i, c] - posterior[c]
            prior_deviation[i, a] = _wrap(prior) if angles[c] else prior
            proposal_deviation[i, a] = _wrap(proposal) if angles[c] else proposal
    return OK


@_jit
def weigh_kernel(
    previous: FloatArray,
    residual: FloatArray,
    mixture: FloatArray,
    variances: FloatArray,
    outliers: bool,
    prior_deviation: FloatArray,
    prior_chol: FloatArray,
    proposal_deviation: FloatArray,
    proposal_chol: FloatArray,
    z_hat: FloatArray,
    z_cov: FloatArray,
    z: FloatArray,
    particles: FloatArray,
    angles: np.ndarray,
    cloud_cov: FloatArray,
    posterior_cov: FloatArray,
    index: np.ndarray,
    fraction: float,
    log_weights: FloatArray,
    own: FloatArray,
    mean: FloatArray,
    spread: FloatArray,
) -> tuple[float, float, float]:
    """The UPF step after its proposal (``upf.UnscentedParticleFilter._weigh`` without resampling): the
    normalised ``log_weights`` (``upf_kernel.log_weights_kernel``), the particles' ``own`` covariance
    (``base.embed`` of (1 - f) ``posterior_cov``), their weighted ``mean`` and ``spread``
    (``base.weighted_moments``). Returns (the largest unnormalised log-weight: not finite when every particle
    is lost, the rest then not computed; the innovation's NIS against the prior mixture, NaN when its
    covariance has no Cholesky factor; the effective sample size)."""
    count, m = z_hat.shape
    dim = particles.shape[1]
    top = log_weights_kernel(
        previous,
        residual,
        mixture,
        variances,
        outliers,
        prior_deviation,
        prior_chol,
        proposal_deviation,
        proposal_chol,
        log_weights,
    )
    if not math.isfinite(top):
        return top, math.nan, math.nan
    # NIS of the innovation against the prior mixture's predicted measurement (upf._innovation_score)
    prior = np.empty(count)
    for i in range(count):
        prior[i] = math.exp(previous[i])
    centre = np.zeros(m)
    for i in range(count):
        for j in range(m):
            centre[j] += prior[i] * z_hat[i, j]
    deviation = np.empty((count, m))
    weighted = np.empty((count, m))
    for i in range(count):
        for j in range(m):
            deviation[i, j] = z_hat[i, j] - centre[j]
            weighted[i, j] = deviation[i, j] * prior[i]
    innovation_cov = z_cov + np.dot(weighted.T, deviation)
    root = np.empty((m, m))
    score = math.nan
    if cholesky(innovation_cov, m, root):
        score = 0.0
        work = np.empty(m)
        for j in range(m):
            value = z[j] - centre[j]
            for col in range(j):
                value -= root[j, col] * work[col]
            work[j] = value / root[j, j]
            score += work[j] * work[j]
    # the new weights, their effective sample size, and the cloud's moments
    weights = np.empty(count)
    squares = 0.0
    for i in range(count):
        weights[i] = math.exp(log_weights[i])
        squares += math.exp(2.0 * log_weights[i])
    weighted_moments_into(particles, weights, angles, mean, spread)
    own[:, :] = cloud_cov
    k = index.size
    for a in range(k):
        for c in range(dim):
            own[index[a], c] = 0.0
            own[c, index[a]] = 0.0
    for a in range(k):
        for b in range(k):
            own[index[a], index[b]] = (1.0 - fraction) * posterior_cov[a, b]
    return top, score, 1.0 / squares


class Proposal(NamedTuple):
    """A UPF step up to its weights: the particles propagated (``centres``, N x D), the shared posterior
    covariance (k, k; (N, k, k) per particle in the reference's unshared form) and the proposal's and
    prior's lower factors, each particle's predicted measurement (N, m) and its covariance, the samples
    (N, D), the particles kept (posterior mean + sqrt(f) of the sample's deviation, N x D) and the samples'
    deviations (N, k) from the prior centres and from the posterior means."""

    centres: np.ndarray
    posterior_cov: np.ndarray
    proposal_chol: np.ndarray
    prior_chol: np.ndarray
    z_hat: np.ndarray
    z_cov: np.ndarray
    sampled: np.ndarray
    particles: np.ndarray
    prior_deviation: np.ndarray
    proposal_deviation: np.ndarray


@functools.cache
def _sigma_weights(k: int) -> tuple[FloatArray, FloatArray, float]:
    """``SigmaWeights(k)``'s mean and covariance weights (read-only) and its sigma-point scale."""
    weights = SigmaWeights(k)
    mean, cov = weights.mean, weights.cov
    mean.flags.writeable = False
    cov.flags.writeable = False
    return mean, cov, math.sqrt(k + weights.lam)


def _array(values: np.ndarray) -> FloatArray:
    """A writable C-ordered float64 array (the kernels' one signature), copied only when it is not (the
    flags read directly: ``np.require`` costs five times as much, some twenty times a step)."""
    flags = values.flags
    if values.dtype == np.float64 and flags.c_contiguous and flags.writeable:
        return values
    return np.array(values, dtype=np.float64, order="C")


def compiled_proposal(
    cloud: Cloud,
    model: object,
    dt: float,
    active: np.ndarray,
    measurement: Measurement,
    rng: np.random.Generator,
    spread_fraction: float,
) -> Proposal | None:
    """The UPF's shared-linearisation step up to its weights by the kernels, drawing from ``rng`` as the
    numpy step does; None (``rng`` as it was) when the kernels are off, the model is not the GNSS-only one,
    the particles carry no covariance of their own, or a kernel declines."""
    if not isinstance(model, GnssOnlyModel) or len(cloud.particles) < 2 or not compiled_enabled():
        return None
    index = np.flatnonzero(active)
    k, count = len(index), len(cloud.particles)
    mean_weights, cov_weights, scale = _sigma_weights(k)
    mean, _ = cloud.moments(ANGLES)
    states = np.empty((count + 2 * k + 1, DIM))
    predicted_cov = np.empty((k, k))
    prior_chol = np.empty((k, k))
    status = time_update_kernel(
        _array(cloud.particles),
        _array(mean),
        _array(cloud.cov),
        _array(model.process_noise(dt)),
        index,
        ANGLES,
        anchor_array(model.anchor),
        float(dt),
        scale,
        mean_weights,
        cov_weights,
        states,
        predicted_cov,
        prior_chol,
    )
    if status != OK:
        return None
    predictions = _array(measurement.predict(states))
    m = len(measurement.z)
    if predictions.shape != (len(states), m):
        return None
    before = rng.bit_generator.state
    draws = rng.standard_normal((count, k))  # the numbers the numpy step draws as (N, k, 1)
    posterior_cov = np.empty((k, k))
    proposal_chol = np.empty((k, k))
    z_hat = np.empty((count, m))
    z_cov = np.empty((m, m))
    sampled = np.empty((count, DIM))
    particles = np.empty((count, DIM))
    prior_deviation = np.empty((count, k))
    proposal_deviation = np.empty((count, k))
    status = update_kernel(
        predictions,
        states,
        index,
        ANGLES,
        mean_weights,
        cov_weights,
        _array(measurement.z),
        _array(measurement.variances),
        predicted_cov,
        draws,
        math.sqrt(spread_fraction),
        posterior_cov,
        proposal_chol,
        z_hat,
        z_cov,
        sampled,
        particles,
        prior_deviation,
        proposal_deviation,
    )
    if status != OK:
        rng.bit_generator.state = before
        return None
    return Proposal(
        states[:count],
        posterior_cov,
        proposal_chol,
        prior_chol,
        z_hat,
        z_cov,
        sampled,
        particles,
        prior_deviation,
        proposal_deviation,
    )


class Weighed(NamedTuple):
    """A UPF step's weights and new cloud before resampling: normalised log-weights (N,), the NIS of the
    innovation, the particles' own covariance (D, D), the weighted mean and spread of the particles and the
    effective sample size."""

    log_weights: np.ndarray
    score: float
    own: np.ndarray
    mean: np.ndarray
    spread: np.ndarray
    ess: float


def compiled_weights(
    previous: np.ndarray,
    measurement: Measurement,
    residual: np.ndarray,
    proposal: Proposal,
    cloud_cov: np.ndarray,
    active: np.ndarray,
    fraction: float,
) -> Weighed | None:
    """``upf.UnscentedParticleFilter._weigh``'s weights, score, own covariance, moments and effective
    sample size by :func:`weigh_kernel`; None when the kernels are off or the covariances are per particle
    (the caller's numpy runs). Every particle lost raises NumericalError, as ``base.normalise`` does; the
    score is None here when the kernel's innovation covariance has no Cholesky factor (the caller's numpy
    score decides)."""
    if proposal.posterior_cov.ndim != 2 or residual.ndim != 2 or not compiled_enabled():
        return None
    count, dim = proposal.particles.shape
    outliers = measurement.outlier_probability > 0.0
    mixture = (
        np.array(measurement.mixture_terms(), dtype=float) if outliers else np.zeros((4, residual.shape[1]))
    )
    log_weights = np.empty(count)
    own = np.empty((dim, dim))
    mean = np.empty(dim)
    spread = np.empty((dim, dim))
    top, score, ess = weigh_kernel(
        _array(previous),
        _array(residual),
        mixture,
        _array(measurement.variances),
        outliers,
        _array(proposal.prior_deviation),
        _array(proposal.prior_chol),
        _array(proposal.proposal_deviation),
        _array(proposal.proposal_chol),
        _array(proposal.z_hat),
        _array(proposal.z_cov),
        _array(measurement.z),
        _array(proposal.particles),
        ANGLES,
        _array(cloud_cov),
        _array(proposal.posterior_cov),
        np.flatnonzero(active),
        float(fraction),
        log_weights,
        own,
        mean,
        spread,
    )
    if not math.isfinite(top):
        raise NumericalError("every particle has zero weight")
    return Weighed(log_weights, score, own, mean, spread, ess)


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernels' one signature each, on a small cloud of the
    GNSS-only model; returns the seconds."""
    from edgepos.core.motion.riss import GeodeticAnchor

    started = time.perf_counter()
    anchor = GeodeticAnchor(0.7, 0.04, 200.0)
    model = GnssOnlyModel(anchor)
    cloud = Cloud(np.zeros((3, DIM)), np.full(3, -math.log(3.0)), np.eye(DIM))
    measurement = Measurement(lambda states: states[..., :2].copy(), np.zeros(2), np.ones(2))
    proposal = compiled_proposal(cloud, model, 1.0, model.active, measurement, np.random.default_rng(0), 0.02)
    if proposal is not None:
        for outliers in (0.0, 0.05):
            mixed = Measurement(measurement.predict, measurement.z, measurement.variances, outliers, 4.0)
            residual = mixed.z - mixed.predict(proposal.sampled)
            compiled_weights(cloud.log_weights, mixed, residual, proposal, cloud.cov, model.active, 0.02)
    return time.perf_counter() - started
