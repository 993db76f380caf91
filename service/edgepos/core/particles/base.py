"""Shared pieces of the particle filters and the unscented proposal: the cloud, weights, resampling,
batched Gaussian algebra and the unscented transform vectorised over particles.

States are rows of (N, D) arrays; a motion model (see core/motion/riss.py) propagates any leading axes and
names its stochastic components (``active``); angle components (``angles``) are wrapped in differences and
averaged on the circle. Everything is plain numpy with the particle axis first, no Python loop over it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.linalg import solve_triangular

from edgepos.core.errors import NumericalError
from edgepos.core.numerics import FloatArray

_LOG_2PI = math.log(2.0 * math.pi)


class ParticleModel(Protocol):
    """What the filters need of a motion model."""

    active: np.ndarray

    def propagate(self, states: np.ndarray, dt: float) -> np.ndarray: ...

    def process_noise(self, dt: float) -> np.ndarray: ...

    def complete(self, states: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class Measurement:
    """Observed values ``z`` (m,), their noise variances (m,) and the prediction function of states.

    ``outlier_probability`` > 0 makes each component's likelihood, in the particle filters' weights, the
    mixture (1 - p) N(r; 0, variance) + p N(r; 0, ``outlier_variance``): a heavy tail for errors the
    Gaussian does not model (reflected signals). ``outlier_variance`` is one value or one per component
    (measurements of different units stacked). The unscented updates (UKF, the UPF's proposal) stay
    Gaussian.
    """

    predict: Callable[[np.ndarray], np.ndarray]
    z: np.ndarray
    variances: np.ndarray
    outlier_probability: float = 0.0
    outlier_variance: float | np.ndarray = 0.0

    def log_likelihood(self, residual: np.ndarray) -> np.ndarray:
        """log p(z | x) for residuals z - h(x) (..., m), summed over the last axis."""
        if self.outlier_probability <= 0.0:
            return diagonal_logpdf(residual, self.variances)
        total: FloatArray = np.sum(self.component_log_likelihoods(residual), axis=-1)
        return total

    def component_log_likelihoods(self, residual: np.ndarray) -> np.ndarray:
        """log of each component's mixture density (..., m)."""
        inlier_scale, inlier_offset, outlier_scale, outlier_offset = self._mixture
        squared = residual * residual
        mixture: FloatArray = np.logaddexp(
            squared * inlier_scale + inlier_offset, squared * outlier_scale + outlier_offset
        )
        return mixture

    def mixture_terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The mixture's two log-densities per component as (inlier a, inlier b, outlier a, outlier b) of
        a r^2 + b, each (m,) (what the compiled UPF weights read; computed once per measurement)."""
        return self._mixture

    @functools.cached_property
    def _mixture(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The two Gaussians' log-densities as a r^2 + b per component, computed once per measurement: log
        (1 - p) - (r^2 / v + log v + log 2 pi) / 2 for the inlier, the same with p and the outlier variance."""
        p = self.outlier_probability
        outlier = np.broadcast_to(np.asarray(self.outlier_variance, float), self.variances.shape)
        return (
            -0.5 / self.variances,
            math.log1p(-p) - 0.5 * (np.log(self.variances) + _LOG_2PI),
            -0.5 / outlier,
            math.log(p) - 0.5 * (np.log(outlier) + _LOG_2PI),
        )


@dataclass
class Cloud:
    """Particles (N, D), their normalised log-weights (N,) and a covariance (D, D): each particle's own
    covariance, shared by all (UPF, UKF), or the weighted spread of the cloud (PF)."""

    particles: np.ndarray
    log_weights: np.ndarray
    cov: np.ndarray

    @property
    def weights(self) -> np.ndarray:
        weights: FloatArray = np.exp(self.log_weights)
        return weights

    def moments(self, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`weighted_moments` of the particles with their weights, computed once per cloud: the
        pipeline's prediction and the UPF's time update both start from them. Remembered with the arrays
        and ``angles`` they came from (a cloud given new arrays computes them again) and returned read-only,
        as the arrays of a cloud are never changed in place (each step makes a new cloud)."""
        known = self.known_moments(angles)
        if known is not None:
            return known
        mean, cov = weighted_moments(self.particles, self.weights, angles)
        return self.remember_moments(angles, mean, cov)

    def known_moments(self, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """:meth:`moments` when they are already known for the cloud's arrays and ``angles``, else None
        (nothing is computed)."""
        cached = self.__dict__.get("_moments")
        if (
            cached is None
            or cached[0] is not self.particles
            or cached[1] is not self.log_weights
            or cached[2] is not angles
        ):
            return None
        known: tuple[np.ndarray, np.ndarray] = cached[3]
        return known

    def remember_moments(
        self, angles: np.ndarray, mean: np.ndarray, cov: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Take (read-only copies of) ``mean`` and ``cov`` as :meth:`moments` for the cloud's arrays and
        ``angles``: for a caller that has just computed ``weighted_moments`` of exactly these particles with
        exp(log_weights) (a filter step; or its compiled equivalent, ``upf_step_kernel.weigh_kernel``, equal
        to rounding), or read them back with the cloud's state. Returns the copies."""
        mean, cov = np.array(mean, dtype=float), np.array(cov, dtype=float)
        mean.flags.writeable = False
        cov.flags.writeable = False
        self.__dict__["_moments"] = (self.particles, self.log_weights, angles, (mean, cov))
        return mean, cov


@dataclass(frozen=True)
class StepResult:
    """A filter step: the new cloud, the estimate (mean, cov), the innovation's normalised squared
    length (None without a measurement), the effective sample size before resampling, and whether the
    cloud was resampled."""

    cloud: Cloud
    mean: np.ndarray
    cov: np.ndarray
    nis: float | None
    ess: float
    resampled: bool


def normalise(log_weights: np.ndarray) -> np.ndarray:
    """Log-weights shifted so that the weights sum to one; a cloud that lost every particle raises."""
    top = float(np.max(log_weights))
    if not math.isfinite(top):
        raise NumericalError("every particle has zero weight")
    shifted = log_weights - top
    return shifted - math.log(float(np.sum(np.exp(shifted))))


def effective_sample_size(log_weights: np.ndarray) -> float:
    """1 / sum(w^2) of normalised weights."""
    return float(1.0 / np.sum(np.exp(2.0 * log_weights)))


def systematic_resample(log_weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of the particles kept by systematic resampling (one uniform draw)."""
    count = len(log_weights)
    cumulative = np.cumsum(np.exp(log_weights))
    cumulative[-1] = 1.0
    positions = (rng.random() + np.arange(count)) / count
    return np.searchsorted(cumulative, positions, side="left")


def wrap(values: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Wrap the angle columns (boolean mask over the last axis) of differences to [-pi, pi)."""
    if angles.any():
        values = values.copy()
        values[..., angles] = (values[..., angles] + math.pi) % (2.0 * math.pi) - math.pi
    return values


def weighted_moments(
    points: np.ndarray, weights: np.ndarray, angles: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of rows (N, D) with weights (N,) summing to one; circular mean for angles."""
    mean = weights @ points
    if angles.any():
        mean[angles] = np.arctan2(weights @ np.sin(points[:, angles]), weights @ np.cos(points[:, angles]))
    deviation = wrap(points - mean, angles)
    cov = (deviation * weights[:, None]).T @ deviation
    return mean, 0.5 * (cov + cov.T)


def batched_cholesky(matrices: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors of a stack of covariances (..., k, k), repairing nearly singular ones with a
    growing diagonal jitter; non-finite or clearly indefinite input raises NumericalError."""
    if not np.all(np.isfinite(matrices)):
        raise NumericalError("covariance has non-finite entries")
    try:
        return np.linalg.cholesky(matrices)
    except np.linalg.LinAlgError:
        pass
    sym = 0.5 * (matrices + np.swapaxes(matrices, -1, -2))
    scale = np.maximum(np.max(np.abs(np.diagonal(sym, axis1=-2, axis2=-1)), axis=-1), 1e-300)
    identity = np.eye(sym.shape[-1])
    for relative in (1e-12, 1e-10, 1e-8, 1e-6):
        try:
            return np.linalg.cholesky(sym + (relative * scale)[..., None, None] * identity)
        except np.linalg.LinAlgError:
            continue
    values, vectors = np.linalg.eigh(sym)
    if np.any(values.min(axis=-1) < -1e-6 * scale):
        raise NumericalError("covariance is indefinite")
    clipped = np.maximum(values, 1e-9 * scale[..., None])
    return np.linalg.cholesky((vectors * clipped[..., None, :]) @ np.swapaxes(vectors, -1, -2))


def gaussian_logpdf(deviation: np.ndarray, chol: np.ndarray) -> np.ndarray:
    """log N(deviation; 0, L L^T) for deviations (..., k) and lower factors (k, k) or (..., k, k)."""
    if chol.ndim == 2:  # one factor for all: one triangular solve, not a batch of general ones
        flat = deviation.reshape(-1, deviation.shape[-1])
        whitened = solve_triangular(chol, flat.T, lower=True, check_finite=False).T.reshape(deviation.shape)
    else:
        whitened = np.linalg.solve(chol, deviation[..., None])[..., 0]
    log_det = np.sum(np.log(np.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
    k = deviation.shape[-1]
    log_pdf: FloatArray = -0.5 * np.sum(whitened * whitened, axis=-1) - log_det - 0.5 * k * _LOG_2PI
    return log_pdf


def diagonal_logpdf(residual: np.ndarray, variances: np.ndarray) -> np.ndarray:
    """log N(residual; 0, diag(variances)) over the last axis."""
    log_pdf: FloatArray = -0.5 * np.sum(
        residual * residual / variances + np.log(variances) + _LOG_2PI, axis=-1
    )
    return log_pdf


@dataclass(frozen=True)
class SigmaWeights:
    """Unscented transform weights (eq. 9) for k stochastic dimensions: spread alpha, prior beta, kappa."""

    k: int
    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    @property
    def lam(self) -> float:
        return self.alpha**2 * (self.k + self.kappa) - self.k

    @property
    def mean(self) -> np.ndarray:
        w = np.full(2 * self.k + 1, 1.0 / (2.0 * (self.k + self.lam)))
        w[0] = self.lam / (self.k + self.lam)
        return w

    @property
    def cov(self) -> np.ndarray:
        w = self.mean.copy()
        w[0] += 1.0 - self.alpha**2 + self.beta
        return w


def sigma_points(
    means: np.ndarray, chols: np.ndarray, active: np.ndarray, weights: SigmaWeights
) -> np.ndarray:
    """Eq. 10 for every particle: (N, 2k+1, D) points around means (N, D) along the columns of
    sqrt(k + lambda) L, L (k, k) shared or (N, k, k) per particle, in the ``active`` components."""
    _count, _dim = means.shape
    k = weights.k
    scaled = math.sqrt(k + weights.lam) * chols
    columns = np.swapaxes(scaled, -1, -2)  # row j = column j of L
    points = np.repeat(means[:, None, :], 2 * k + 1, axis=1)
    index = np.flatnonzero(active)
    block = points[:, :, index]
    block[:, 1 : k + 1, :] += columns
    block[:, k + 1 :, :] -= columns
    points[:, :, index] = block
    return points


def sigma_mean(points: np.ndarray, weights: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Weighted mean over the sigma axis (N, S, D) -> (N, D); angles averaged as wrapped offsets from the
    central point."""
    mean: FloatArray = weights @ points
    if angles.any():
        centre = points[:, 0, angles]
        offsets = wrap(points[:, :, angles] - centre[:, None, :], np.ones(int(angles.sum()), dtype=bool))
        mean[:, angles] = centre + weights @ offsets
    return mean


def weighted_outer(weights: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum_s w_s a[n, s, :] b[n, s, :]^T for sigma-point deviations a (N, S, i), b (N, S, j) -> (N, i, j)."""
    outer: FloatArray = np.swapaxes(a * weights[:, None], -1, -2) @ b
    return outer


@dataclass(frozen=True)
class UnscentedStep:
    """Per particle: the deterministic prediction f(x) (N, D), the predicted mean (N, D) and covariance
    (N, k, k) of the active components, and after the update (when a measurement was given) the posterior
    mean (N, D) and covariance (N, k, k), the predicted measurement (N, m) and its covariance (N, m, m)."""

    prior: np.ndarray
    predicted: np.ndarray
    predicted_cov: np.ndarray
    posterior: np.ndarray | None = None
    posterior_cov: np.ndarray | None = None
    z_hat: np.ndarray | None = None
    z_cov: np.ndarray | None = None


@dataclass(frozen=True)
class UnscentedUpdate:
    """The measurement update of N Gaussians: posterior means (N, D) and covariances (N, k, k) of the
    active components, predicted measurements (N, m) and their covariances (N, m, m); the covariances are
    (k, k) and (m, m) when all share them (:func:`shared_unscented_update`)."""

    posterior: np.ndarray
    posterior_cov: np.ndarray
    z_hat: np.ndarray
    z_cov: np.ndarray


def unscented_predict(
    means: np.ndarray,
    cov: np.ndarray | None,
    model: ParticleModel,
    dt: float,
    active: np.ndarray,
    angles: np.ndarray,
    weights: SigmaWeights | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """UKF time update (eq. 11) of N Gaussians (means (N, D), full-state covariance ``cov`` (D, D) shared,
    or None for points): (f of each mean (N, D), predicted means (N, D), covariances (N, k, k))."""
    index = np.flatnonzero(active)
    weights = weights or SigmaWeights(len(index))
    q = model.process_noise(dt)[np.ix_(index, index)]
    if cov is None or not np.any(cov[np.ix_(index, index)]):
        # A point prior: the time update is f(x) with covariance Q.
        prior = model.propagate(means, dt)
        return prior, prior.copy(), np.broadcast_to(q, (len(means),) + q.shape).copy()
    chol = batched_cholesky(cov[np.ix_(index, index)])
    points = model.propagate(sigma_points(means, chol, active, weights), dt)
    predicted = model.complete(sigma_mean(points, weights.mean, angles))
    deviation = wrap(points[:, :, index] - predicted[:, None, index], angles[index])
    predicted_cov = q + weighted_outer(weights.cov, deviation, deviation)
    return points[:, 0, :], predicted, predicted_cov


def unscented_update(
    predicted: np.ndarray,
    predicted_cov: np.ndarray,
    model: ParticleModel,
    active: np.ndarray,
    angles: np.ndarray,
    measurement: Measurement,
    weights: SigmaWeights | None = None,
) -> UnscentedUpdate:
    """UKF measurement update (eqs. 12-14) of N Gaussians: means (N, D), active-block covariances (k, k)
    shared or (N, k, k). Sigma points are drawn around the prediction, so the process noise enters the
    innovation. A singular innovation covariance raises NumericalError."""
    index = np.flatnonzero(active)
    weights = weights or SigmaWeights(len(index))
    wm, wc = weights.mean, weights.cov
    active_angles = angles[index]
    points = sigma_points(predicted, batched_cholesky(predicted_cov), active, weights)
    z_points = measurement.predict(points)
    z_hat = wm @ z_points
    dz = z_points - z_hat[:, None, :]
    dx = wrap(points[:, :, index] - predicted[:, None, index], active_angles)
    z_cov = weighted_outer(wc, dz, dz) + np.diag(measurement.variances)
    cross = weighted_outer(wc, dx, dz)
    innovation = measurement.z - z_hat
    posterior = predicted.copy()
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):  # non-finite results raise below
        try:
            gain = np.swapaxes(np.linalg.solve(z_cov, np.swapaxes(cross, -1, -2)), -1, -2)  # (N, k, m)
        except np.linalg.LinAlgError:
            raise NumericalError("singular innovation covariance") from None
        posterior[:, index] += (gain @ innovation[:, :, None])[:, :, 0]
        posterior_cov = predicted_cov - gain @ np.swapaxes(cross, -1, -2)  # P - K S K^T with K S = cross
    if active_angles.any():
        posterior[:, index] = wrap(posterior[:, index], active_angles)
    posterior = model.complete(posterior)
    posterior_cov = 0.5 * (posterior_cov + np.swapaxes(posterior_cov, -1, -2))
    if not (np.all(np.isfinite(posterior)) and np.all(np.isfinite(posterior_cov))):
        raise NumericalError("the measurement update is not finite")
    return UnscentedUpdate(posterior, posterior_cov, z_hat, z_cov)


def shared_unscented_update(
    predicted: np.ndarray,
    predicted_cov: np.ndarray,
    model: ParticleModel,
    active: np.ndarray,
    angles: np.ndarray,
    measurement: Measurement,
    reference: np.ndarray,
    weights: SigmaWeights | None = None,
) -> UnscentedUpdate:
    """:func:`unscented_update` of N Gaussians that share one covariance (k, k), with the sigma-point
    deviations taken once, around ``reference`` (D,), instead of around every mean.

    With a shared covariance the state deviations of the sigma points are the same for every particle;
    their measurement deviations differ only through h's curvature over the distance between the particles
    (metres, against 20,000 km to a satellite: micrometres of range). So one innovation covariance, gain
    and posterior covariance serve all, and each particle's predicted measurement is h at its own mean plus
    the reference's second-order sigma-point term. h is evaluated at N + 2k + 1 states instead of
    N (2k + 1), and one (m, m) system is solved instead of N. Exact for a linear h. Returns the posterior
    means (N, D), and the posterior covariance (k, k), predicted measurements (N, m) and their covariance
    (m, m) shared by all."""
    index = np.flatnonzero(active)
    weights = weights or SigmaWeights(len(index))
    wm, wc = weights.mean, weights.cov
    active_angles = angles[index]
    count = len(predicted)
    points = sigma_points(reference[None, :], batched_cholesky(predicted_cov), active, weights)[0]
    predictions = measurement.predict(np.concatenate([predicted, points]))
    z_points = predictions[count:]
    z_ref = wm @ z_points
    z_hat = predictions[:count] + (z_ref - z_points[0])
    dz = z_points - z_ref
    dx = wrap(points[:, index] - reference[index], active_angles)
    z_cov = (dz.T * wc) @ dz + np.diag(measurement.variances)
    cross = (dx.T * wc) @ dz
    posterior = predicted.copy()
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):  # non-finite results raise below
        try:
            gain = np.linalg.solve(z_cov, cross.T).T  # (k, m)
        except np.linalg.LinAlgError:
            raise NumericalError("singular innovation covariance") from None
        posterior[:, index] += (measurement.z - z_hat) @ gain.T
        posterior_cov = predicted_cov - gain @ cross.T
    if active_angles.any():
        posterior[:, index] = wrap(posterior[:, index], active_angles)
    posterior = model.complete(posterior)
    posterior_cov = 0.5 * (posterior_cov + posterior_cov.T)
    if not (np.all(np.isfinite(posterior)) and np.all(np.isfinite(posterior_cov))):
        raise NumericalError("the measurement update is not finite")
    return UnscentedUpdate(posterior, posterior_cov, z_hat, z_cov)


def unscented_step(
    means: np.ndarray,
    cov: np.ndarray | None,
    model: ParticleModel,
    dt: float,
    active: np.ndarray,
    angles: np.ndarray,
    measurement: Measurement | None,
    weights: SigmaWeights | None = None,
) -> UnscentedStep:
    """Eqs. 9-14 for N Gaussians at once: UKF time update of each mean (with covariance ``cov`` of the
    full state, shared, (D, D); None for a point) and, given a measurement, the measurement update."""
    prior, predicted, predicted_cov = unscented_predict(means, cov, model, dt, active, angles, weights)
    if measurement is None:
        return UnscentedStep(prior, predicted, predicted_cov)
    update = unscented_update(predicted, predicted_cov, model, active, angles, measurement, weights)
    return UnscentedStep(
        prior, predicted, predicted_cov, update.posterior, update.posterior_cov, update.z_hat, update.z_cov
    )


def kernel_bandwidth(count: int, dim: int) -> float:
    """Optimal Gaussian-kernel bandwidth of a regularised particle filter (Musso, Oudjane & Le Gland
    2001): h = (4 / (N (d + 2)))^(1 / (d + 4))."""
    return float((4.0 / (count * (dim + 2.0))) ** (1.0 / (dim + 4.0)))


def kernel_prior(
    particles: np.ndarray,
    log_weights: np.ndarray,
    active: np.ndarray,
    angles: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The weighted cloud as a Gaussian-kernel mixture that keeps its mean and covariance (Liu & West
    2001): kernel centres a x_i + (1 - a) mean and kernel covariance h^2 Sigma on the active components,
    a = sqrt(1 - h^2). Sampling from the mixture keeps a resampled cloud from collapsing onto copies of
    a few particles (regularisation) without inflating it. Returns (centres (N, D), covariance (k, k))."""
    index = np.flatnonzero(active)
    count = len(particles)
    if count < 2:
        return particles.copy(), np.zeros((len(index), len(index)))
    h = kernel_bandwidth(count, len(index))
    mean, spread = weighted_moments(particles, np.exp(log_weights), angles)
    shrink = math.sqrt(1.0 - h * h)
    centres = particles.copy()
    deviation = wrap(particles[:, index] - mean[index], angles[index])
    centres[:, index] = wrap(mean[index] + shrink * deviation, angles[index])
    return centres, h * h * spread[np.ix_(index, index)]


def regularised_resample(
    particles: np.ndarray,
    log_weights: np.ndarray,
    active: np.ndarray,
    angles: np.ndarray,
    rng: np.random.Generator,
    kernel: bool = True,
) -> np.ndarray:
    """Resample (systematic) without losing the cloud's spread: N equally weighted particles whose mean
    and covariance on the active components are exactly those the weighted cloud stands for.

    Resampling alone shrinks the cloud: the weighted covariance about the weighted mean is biased low by
    the factor 1 - sum(w^2) (about 1 / ESS), and drawing N particles loses another 1 / N in expectation.
    Once per step that is nothing; compounded over the hundreds of resamplings of a drive (progressive
    correction resamples several times per epoch) it collapses every component the measurements do not pin
    - the gyro bias, the wheel scale, the cross-track position - far below the posterior's spread. So the
    resampled cloud (with the Liu-West kernel when ``kernel``) is mapped affinely onto the weighted cloud's
    mean and unbiased covariance Sigma_w / (1 - sum(w^2)). Components without spread are left alone."""
    count = len(particles)
    weights = np.exp(log_weights)
    mean, cov = weighted_moments(particles, weights, angles)
    unbiased = 1.0 - float(np.sum(weights * weights))
    resampled: FloatArray = particles[systematic_resample(log_weights, rng)]
    uniform = np.full(count, -math.log(count))
    index = np.flatnonzero(active)
    if kernel:
        centres, kernel_cov = kernel_prior(resampled, uniform, active, angles)
        resampled = centres
        resampled[:, index] += rng.standard_normal((count, len(index))) @ batched_cholesky(kernel_cov).T
        resampled = wrap(resampled, angles)
    if count < 2 or unbiased <= 0.0:
        return resampled
    new_mean, new_cov = weighted_moments(resampled, np.exp(uniform), angles)
    spread = index[(np.diag(cov)[index] > 0.0) & (np.diag(new_cov)[index] > 0.0)]
    if spread.size == 0:
        return resampled
    block = np.ix_(spread, spread)
    try:
        source = np.linalg.cholesky(new_cov[block])
        target = np.linalg.cholesky(cov[block] / unbiased)
    except np.linalg.LinAlgError:
        return resampled  # too few distinct particles to map: keep them as drawn
    deviation = wrap(resampled[:, spread] - new_mean[spread], angles[spread])
    whitened = np.linalg.solve(source, deviation.T)
    out = resampled.copy()
    out[:, spread] = mean[spread] + (target @ whitened).T
    return wrap(out, angles)


def embed(previous: np.ndarray, block: np.ndarray, active: np.ndarray) -> np.ndarray:
    """A (D, D) covariance: ``block`` (k, k) on the active components, ``previous`` on the others,
    no correlation between the two groups."""
    cov = previous.copy()
    index = np.flatnonzero(active)
    cov[index, :] = 0.0
    cov[:, index] = 0.0
    cov[np.ix_(index, index)] = block
    return cov


def nis(innovation: np.ndarray, cov: np.ndarray) -> float:
    """Normalised innovation squared nu^T S^-1 nu; a singular S raises NumericalError."""
    try:
        return float(innovation @ np.linalg.solve(cov, innovation))
    except np.linalg.LinAlgError:
        raise NumericalError("singular innovation covariance") from None
