"""The particle filters of the gnss_tight pipeline (core/particles) on small problems with known answers:
the unscented update equals the Kalman filter on a linear model, the UPF's weights are the predictive
likelihood (not collapsed onto one particle) and its cloud stands for the Kalman posterior, the
regularisation kernel keeps the cloud's moments, the PF's cloud survives a likelihood much sharper than
itself, and singular steps raise typed errors."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from edgepos.core.errors import NumericalError
from edgepos.core.motion import riss as layout
from edgepos.core.particles import Cloud, Measurement, ParticleFilter, UnscentedParticleFilter
from edgepos.core.particles.base import (
    batched_cholesky,
    effective_sample_size,
    kernel_prior,
    normalise,
    regularised_resample,
    unscented_update,
    weighted_moments,
)
from edgepos.core.particles.upf import predicted_own_covariance

N, E, VE, VN = layout.NORTH, layout.EAST, layout.VE, layout.VN
ACTIVE = np.zeros(layout.DIM, dtype=bool)
ACTIVE[[N, E, VE, VN]] = True
INDEX = np.flatnonzero(ACTIVE)


@dataclass(frozen=True)
class ConstantVelocity:
    """A linear model on four components of the pipeline's state (the others held): constant velocity
    with white-noise acceleration of density ``q``."""

    q: float = 0.01
    active = ACTIVE

    def propagate(self, states: np.ndarray, dt: float) -> np.ndarray:
        out = states.copy()
        out[..., N] += states[..., VN] * dt
        out[..., E] += states[..., VE] * dt
        return out

    def process_noise(self, dt: float) -> np.ndarray:
        q = np.zeros((layout.DIM, layout.DIM))
        for pos, vel in ((N, VN), (E, VE)):
            q[pos, pos] = self.q * dt**3 / 3.0
            q[pos, vel] = q[vel, pos] = self.q * dt**2 / 2.0
            q[vel, vel] = self.q * dt
        return q

    def complete(self, states: np.ndarray) -> np.ndarray:
        return states

    def transition(self, dt: float) -> np.ndarray:
        f = np.eye(len(INDEX))
        f[0, 2] = f[1, 3] = 0.0
        f[INDEX.tolist().index(N), INDEX.tolist().index(VN)] = dt
        f[INDEX.tolist().index(E), INDEX.tolist().index(VE)] = dt
        return f


H = np.zeros((3, len(INDEX)))
H[0, 0] = 1.0  # north
H[1, 1] = 1.0  # east
H[2, 0], H[2, 1] = 0.6, 0.8  # a range-like combination


def linear_measurement(z: np.ndarray, variances: np.ndarray) -> Measurement:
    return Measurement(lambda states: states[..., INDEX] @ H.T, z, variances)


def kalman_update(mean: np.ndarray, cov: np.ndarray, z: np.ndarray, r: np.ndarray):
    s = H @ cov @ H.T + np.diag(r)
    gain = cov @ H.T @ np.linalg.inv(s)
    return mean + gain @ (z - H @ mean), cov - gain @ s @ gain.T, s


def state(north: float, east: float, ve: float, vn: float) -> np.ndarray:
    x = np.zeros(layout.DIM)
    x[[N, E, VE, VN]] = north, east, ve, vn
    return x


def test_unscented_update_equals_the_kalman_filter_on_a_linear_model():
    rng = np.random.default_rng(3)
    means = np.stack([state(*rng.normal(0.0, 5.0, 4)) for _ in range(5)])
    a = rng.normal(size=(4, 4))
    cov = a @ a.T + np.eye(4)
    z, r = np.array([1.0, -2.0, 0.5]), np.array([0.5, 2.0, 1.0])
    update = unscented_update(means, cov, ConstantVelocity(), ACTIVE, layout.ANGLES, linear_measurement(z, r))
    for i in range(len(means)):
        expected_mean, expected_cov, expected_s = kalman_update(means[i, INDEX], cov, z, r)
        np.testing.assert_allclose(update.posterior[i, INDEX], expected_mean, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(update.posterior_cov[i], expected_cov, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(update.z_cov[i], expected_s, rtol=1e-9, atol=1e-9)


def test_kernel_prior_keeps_the_weighted_mean_and_covariance():
    rng = np.random.default_rng(4)
    particles = np.stack([state(*rng.normal(0.0, [3.0, 1.0, 0.5, 2.0])) for _ in range(300)])
    log_weights = normalise(rng.normal(0.0, 1.0, 300))
    centres, kernel = kernel_prior(particles, log_weights, ACTIVE, layout.ANGLES)
    weights = np.exp(log_weights)
    mean, cov = weighted_moments(particles, weights, layout.ANGLES)
    centre_mean, centre_cov = weighted_moments(centres, weights, layout.ANGLES)
    np.testing.assert_allclose(centre_mean[INDEX], mean[INDEX], atol=1e-12)
    block = np.ix_(INDEX, INDEX)
    np.testing.assert_allclose(centre_cov[block] + kernel, cov[block], atol=1e-12)
    assert np.all(np.linalg.eigvalsh(kernel) > 0.0)


def test_upf_weights_are_the_predictive_likelihood_on_a_linear_model():
    """For a linear-Gaussian model likelihood x prior / proposal = N(z; H c_i, H P H^T + R) whatever the
    sample: the UPF's new weights must be exactly that (the paper's literal form, with a proposal of metres
    and a transition density of one step's Q, gave one particle all the weight). Each particle keeps
    (1 - f) of the Kalman posterior covariance as its own, and its centre is the Kalman posterior mean plus
    sqrt(f) of its sample's deviation."""
    rng = np.random.default_rng(5)
    model, dt, fraction = ConstantVelocity(), 1.0, 0.25
    particles = np.stack([state(*rng.normal(0.0, [2.0, 2.0, 0.5, 0.5])) for _ in range(50)])
    log_weights = normalise(rng.normal(0.0, 0.3, 50))
    own = np.zeros((layout.DIM, layout.DIM))
    own[np.ix_(INDEX, INDEX)] = np.diag([0.3, 0.3, 0.1, 0.1])
    cloud = Cloud(particles, log_weights, own)
    z, r = np.array([0.5, -0.5, 0.2]), np.array([1.0, 1.0, 1.0])

    result = UnscentedParticleFilter(resample_threshold=0.0, spread_fraction=fraction).step(
        cloud, model, dt, ACTIVE, linear_measurement(z, r), np.random.default_rng(6)
    )
    centres = model.propagate(particles, dt)
    f = model.transition(dt)
    block = np.ix_(INDEX, INDEX)
    prior_cov = f @ own[block] @ f.T + model.process_noise(dt)[block]
    np.testing.assert_allclose(predicted_own_covariance(cloud, model, dt, ACTIVE), prior_cov, atol=1e-9)
    s = H @ prior_cov @ H.T + np.diag(r)
    innovation = z - centres[:, INDEX] @ H.T
    predictive = -0.5 * np.einsum("ni,ij,nj->n", innovation, np.linalg.inv(s), innovation)
    np.testing.assert_allclose(result.cloud.log_weights, normalise(log_weights + predictive), atol=1e-8)
    _, posterior_cov, _ = kalman_update(np.zeros(4), prior_cov, z, r)
    np.testing.assert_allclose(result.cloud.cov[block], (1.0 - fraction) * posterior_cov, atol=1e-9)
    # Centres: Kalman posterior means plus sqrt(f) of a draw from the posterior covariance.
    means = np.stack([kalman_update(c[INDEX], prior_cov, z, r)[0] for c in centres])
    deviations = (result.cloud.particles[:, INDEX] - means).T
    whitened = np.linalg.solve(np.linalg.cholesky(fraction * posterior_cov), deviations)
    assert 0.5 < np.mean(whitened**2) < 1.5


def upf_beside_kalman(fraction: float, count: int, start: np.ndarray, steps: int, seed: int):
    """Run a UPF whose particles start together with covariance ``start`` (4, 4) and the Kalman filter on the
    same measurements of a constant-velocity truth; yield (UPF step result, Kalman mean, Kalman covariance)
    after each update."""
    model, dt = ConstantVelocity(), 1.0
    rng = np.random.default_rng(seed)
    f = model.transition(dt)
    block = np.ix_(INDEX, INDEX)
    q = model.process_noise(dt)[block]
    mean, cov = np.zeros(4), start
    own = np.zeros((layout.DIM, layout.DIM))
    own[block] = start
    cloud = Cloud(np.zeros((count, layout.DIM)), np.full(count, -math.log(count)), own)
    upf = UnscentedParticleFilter(spread_fraction=fraction)
    truth = np.array([0.0, 0.0, 1.0, -1.0])
    for _ in range(steps):
        truth = f @ truth
        z = H @ truth + rng.normal(0.0, 1.0, 3)
        result = upf.step(cloud, model, dt, ACTIVE, linear_measurement(z, np.ones(3)), rng)
        cloud = result.cloud
        mean, cov, _ = kalman_update(f @ mean, f @ cov @ f.T + q, z, np.ones(3))
        yield result, mean, cov


def test_upf_without_spread_is_the_kalman_filter_on_a_linear_model():
    """Particles that start together and keep none of their samples' spread stay one Gaussian: the UPF's
    estimate must then be the Kalman filter's, mean and covariance, step after step."""
    block = np.ix_(INDEX, INDEX)
    for result, mean, cov in upf_beside_kalman(0.0, 20, np.diag([4.0, 4.0, 1.0, 1.0]), 8, seed=11):
        np.testing.assert_allclose(result.mean[INDEX], mean, atol=1e-9)
        np.testing.assert_allclose(result.cov[block], cov, atol=1e-9)


@pytest.mark.parametrize("fraction", [0.02, 0.5, 1.0])
def test_upf_cloud_stands_for_the_kalman_posterior_whatever_its_spread(fraction: float) -> None:
    """However the uncertainty is split between the particles' spread and their own covariance, the cloud's
    mean and covariance (spread + own) follow the Kalman posterior of a linear model."""
    block = np.ix_(INDEX, INDEX)
    *_, (result, mean, cov) = upf_beside_kalman(fraction, 2000, np.diag([9.0, 9.0, 1.0, 1.0]), 6, seed=12)
    position = np.ix_([0, 1], [0, 1])
    np.testing.assert_allclose(result.mean[INDEX][:2], mean[:2], atol=0.1)
    np.testing.assert_allclose(result.cov[block][position], cov[position], rtol=0.15, atol=0.02)
    if fraction < 1.0:
        assert np.trace(result.cloud.cov[block]) > 0.0


def test_upf_effective_sample_size_stays_high_when_the_process_noise_is_tiny():
    """The pipeline's regime: one step's process noise of centimetres, pseudorange-like noise of a metre,
    a cloud of metres. The ESS must not fall to one particle (it was 1 of 200 at every update)."""
    model, dt, count = ConstantVelocity(q=1e-6), 1.0, 200
    rng = np.random.default_rng(7)
    truth = state(0.0, 0.0, 10.0, 0.0)
    start = np.zeros((layout.DIM, layout.DIM))
    start[np.ix_(INDEX, INDEX)] = np.diag([9.0, 9.0, 4.0, 4.0])
    cloud = Cloud(np.repeat(truth[None, :], count, axis=0), np.full(count, -math.log(count)), start)
    upf = UnscentedParticleFilter()
    fractions, errors = [], []
    for k in range(30):
        truth = model.propagate(truth[None, :], dt)[0]
        z = H @ truth[INDEX] + rng.normal(0.0, 1.0, 3)
        result = upf.step(cloud, model, dt, ACTIVE, linear_measurement(z, np.ones(3)), rng)
        cloud = result.cloud
        fractions.append(result.ess / count)
        errors.append(math.hypot(*(result.mean[[N, E]] - truth[[N, E]])))
    assert np.median(fractions) > 0.3, fractions
    assert min(fractions) > 0.05, fractions
    assert np.sqrt(np.mean(np.square(errors[10:]))) < 1.0


def test_pf_cloud_survives_a_likelihood_much_sharper_than_itself():
    """A cloud 10 m wide meets measurements of 0.3 m: one weighting leaves about one particle, after which a
    bootstrap PF cannot spread again. With progressive correction the cloud keeps its particles and its
    spread matches the Kalman posterior's."""
    model, dt, count = ConstantVelocity(q=1e-6), 1.0, 500
    rng = np.random.default_rng(8)
    prior = np.diag([100.0, 100.0, 1.0, 1.0])
    particles = np.zeros((count, layout.DIM))
    particles[:, INDEX] = rng.multivariate_normal(np.zeros(4), prior, count)
    cloud = Cloud(particles, np.full(count, -math.log(count)), np.eye(layout.DIM))
    r = np.full(3, 0.09)
    z = np.array([1.0, 2.0, 2.2])
    result = ParticleFilter().step(cloud, model, dt, ACTIVE, linear_measurement(z, r), rng)
    f = model.transition(dt)
    predicted_cov = f @ prior @ f.T + model.process_noise(dt)[np.ix_(INDEX, INDEX)]
    mean, cov, _ = kalman_update(np.zeros(4), predicted_cov, z, r)
    assert result.ess > 0.3 * count
    distinct = len(np.unique(result.cloud.particles[:, N]))
    assert distinct > 0.5 * count
    np.testing.assert_allclose(result.mean[[N, E]], mean[:2], atol=0.15)
    spread = np.sqrt(np.diag(result.cov)[[N, E]])
    expected = np.sqrt(np.diag(cov)[:2])
    assert np.all(spread > 0.5 * expected) and np.all(spread < 2.0 * expected), (spread, expected)


def test_singular_and_non_finite_steps_raise_numerical_error():
    means = np.stack([state(0.0, 0.0, 1.0, 1.0)])
    zero = np.zeros((4, 4))
    # Two identical exact measurements of a known state: the innovation covariance is singular.
    twice = lambda s: np.stack([s[..., N], s[..., N]], axis=-1)
    duplicate = Measurement(twice, np.array([0.0, 0.0]), np.zeros(2))
    with pytest.raises(NumericalError):
        unscented_update(means, zero, ConstantVelocity(), ACTIVE, layout.ANGLES, duplicate)
    with pytest.raises(NumericalError):
        batched_cholesky(np.full((4, 4), np.nan))
    with pytest.raises(NumericalError):
        normalise(np.full(5, -np.inf))
    assert effective_sample_size(normalise(np.zeros(4))) == pytest.approx(4.0)


def test_mixture_likelihood_is_the_gaussian_without_outliers_and_heavy_tailed_with_them():
    from edgepos.core.particles.base import diagonal_logpdf

    residual = np.array([[0.5, -1.0, 30.0], [0.0, 2.0, -3.0]])
    variances = np.array([1.0, 4.0, 1.0])
    plain = linear_measurement(np.zeros(3), variances)
    np.testing.assert_allclose(plain.log_likelihood(residual), diagonal_logpdf(residual, variances))
    mixture = Measurement(plain.predict, np.zeros(3), variances, 0.1, 900.0)
    by_hand = np.sum(
        np.log(
            0.9 * np.exp(-0.5 * residual**2 / variances) / np.sqrt(2.0 * math.pi * variances)
            + 0.1 * np.exp(-0.5 * residual**2 / 900.0) / math.sqrt(2.0 * math.pi * 900.0)
        ),
        axis=-1,
    )
    np.testing.assert_allclose(mixture.log_likelihood(residual), by_hand, rtol=1e-12)
    # A 30-sigma residual costs the mixture a few nats, the Gaussian hundreds.
    assert plain.log_likelihood(residual)[0] - plain.log_likelihood(residual)[1] < -400.0
    assert mixture.log_likelihood(residual)[0] - mixture.log_likelihood(residual)[1] > -10.0


def test_mixture_likelihood_keeps_a_reflected_range_from_dragging_the_pf() -> None:
    """Three range-like measurements of a point at the origin, the third 40 m long (a reflection): with the
    Gaussian likelihood the PF's estimate is pulled metres off, with the mixture it stays within a metre.
    (The UPF's proposal is a Gaussian UKF update, dragged like the Kalman filter; the mixture only reweighs
    its samples, so a single reflection is kept out by the pipeline's snapshot and residual tests.)"""
    model, dt, count = ConstantVelocity(q=1e-6), 1.0, 400
    prior = np.diag([25.0, 25.0, 1.0, 1.0])
    r = np.ones(3)
    z = np.array([0.0, 0.0, 40.0])
    errors = {}
    for p in (0.0, 0.1):
        rng = np.random.default_rng(9)
        particles = np.zeros((count, layout.DIM))
        particles[:, INDEX] = rng.multivariate_normal(np.zeros(4), prior, count)
        cov = np.eye(layout.DIM)
        cloud = Cloud(particles, np.full(count, -math.log(count)), cov)
        measurement = Measurement(linear_measurement(z, r).predict, z, r, p, 900.0 if p else 0.0)
        result = ParticleFilter().step(cloud, model, dt, ACTIVE, measurement, rng)
        errors[p] = math.hypot(*result.mean[[N, E]])
    assert errors[0.0] > 5.0, errors
    assert errors[0.1] < 1.0, errors


def test_regularised_resample_keeps_the_weighted_mean_and_unbiased_covariance():
    rng = np.random.default_rng(11)
    particles = np.stack([state(*rng.normal(0.0, [3.0, 1.0, 0.5, 2.0])) for _ in range(200)])
    log_weights = normalise(rng.normal(0.0, 1.0, 200))
    weights = np.exp(log_weights)
    mean, cov = weighted_moments(particles, weights, layout.ANGLES)
    block = np.ix_(INDEX, INDEX)
    for kernel in (True, False):
        resampled = regularised_resample(particles, log_weights, ACTIVE, layout.ANGLES, rng, kernel=kernel)
        new_mean, new_cov = weighted_moments(resampled, np.full(200, 1 / 200), layout.ANGLES)
        np.testing.assert_allclose(new_mean[INDEX], mean[INDEX], atol=1e-9)
        np.testing.assert_allclose(new_cov[block], cov[block] / (1.0 - np.sum(weights**2)), atol=1e-9)


def test_repeated_resampling_does_not_collapse_the_cloud():
    """Weights that carry no information about the particles must not shrink the cloud however often it
    is resampled. Plain (kernel) resampling lost about 1 / ESS + 1 / N of the covariance each time:
    a 15-dimensional cloud of 200 particles fell to 5e-5 of its variance in 400 resamplings, which is
    how the particle filters' gyro bias, wheel scale and cross-track spread collapsed on a drive."""
    rng = np.random.default_rng(12)
    count, dim = 200, layout.DIM
    active = np.ones(dim, dtype=bool)
    angles = np.zeros(dim, dtype=bool)
    particles = rng.standard_normal((count, dim))
    for cycle in range(400):
        log_weights = normalise(rng.standard_normal(count))
        particles = regularised_resample(particles, log_weights, active, angles, rng, kernel=cycle % 2 == 0)
    variance = float(np.mean(np.var(particles, axis=0)))
    assert 0.05 < variance < 20.0
