"""Unscented particle filter (section 2.2.1, eqs. 8-18), vectorised over particles.

Each particle's prior at a measurement is its own transition density p(x_k | x_i) = N(c_i, P): c_i the
particle propagated deterministically since the last measurement (shrunk towards the cloud's mean, see
below) and P the process noise accumulated over that interval plus the regularisation kernel. The UKF
update of that prior (eqs. 9-14) is the particle's proposal q = N(x_hat_i, P_i) (eq. 15); a sample is drawn
from it and weighted by likelihood x transition / proposal (eq. 16), which for a linear model equals the
predictive likelihood N(z; z_hat_i, S_i) whatever the sample: the weights stay well spread. The estimate is
the weighted mean (eq. 17); the cloud is resampled when the effective sample size is low (eq. 18).

Why not the paper's literal form (each particle's UKF started from a covariance of metres, and the
transition density N(f(x), Q) of one 0.1 s step in the weight): the two densities disagree by orders of
magnitude, so the normalised weights collapse onto one particle at every update. Here the proposal and the
transition density are built from the same prior.

The cloud's stored covariance (``Cloud.cov``) is P: the process noise each particle has accumulated since
the last measurement (zero right after one), shared because the RISS model's noise does not depend on the
state. The regularisation kernel is the same as the PF's (``kernel_prior``): with the UKF proposal it moves
the kernel's samples towards the measurement instead of scattering them blindly.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from edgepos.core.motion.riss import ANGLES
from edgepos.core.particles.base import (
    Cloud,
    Measurement,
    ParticleModel,
    StepResult,
    batched_cholesky,
    embed,
    gaussian_logpdf,
    kernel_prior,
    nis,
    normalise,
    unscented_predict,
    unscented_update,
    weighted_moments,
    wrap,
)
from edgepos.core.particles.pf import _finish


def accumulated_noise(cloud: Cloud, model: ParticleModel, dt: float, active: np.ndarray) -> np.ndarray:
    """The process noise accumulated since the last measurement, carried over ``dt`` (k, k): the UKF time
    update of N(weighted mean, cloud.cov) - the dynamics are nearly linear over one interval, so one
    linearisation point serves every particle."""
    weights = np.exp(cloud.log_weights)
    centre, _ = weighted_moments(cloud.particles, weights, ANGLES)
    _, _, cov = unscented_predict(centre[None, :], cloud.cov, model, dt, active, ANGLES)
    return cov[0]


@dataclass(frozen=True)
class UnscentedParticleFilter:
    """UKF proposal per particle; ``resample_threshold`` is the ESS fraction that triggers resampling."""

    resample_threshold: float = 0.5
    name = "upf"

    def covariance(self, cloud: Cloud) -> np.ndarray:
        """The state covariance the cloud stands for: spread of the particles plus their own noise."""
        _, spread = weighted_moments(cloud.particles, np.exp(cloud.log_weights), ANGLES)
        return spread + cloud.cov

    def step(
        self, cloud: Cloud, model: ParticleModel, dt: float, active: np.ndarray, measurement: Measurement | None,
        rng: np.random.Generator,
    ) -> StepResult:
        index = np.flatnonzero(active)
        count = len(cloud.particles)
        angles = ANGLES[index]
        noise = accumulated_noise(cloud, model, dt, active)
        particles = model.complete(wrap(model.propagate(cloud.particles, dt), ANGLES))
        if measurement is None:
            # No observation: particles move deterministically; their noise accumulates in the shared P.
            accumulated = embed(cloud.cov, noise, active)
            threshold = self.resample_threshold
            pending = accumulated
            result = _finish(particles, cloud.log_weights, pending, active, None, threshold, rng, pending)
            mean, spread = weighted_moments(particles, np.exp(cloud.log_weights), ANGLES)
            return StepResult(result.cloud, mean, spread + accumulated, None, result.ess, result.resampled)

        centres, kernel_cov = kernel_prior(particles, cloud.log_weights, active, ANGLES)
        prior_cov = noise + kernel_cov
        update = unscented_update(centres, prior_cov, model, active, ANGLES, _proposal_measurement(
            measurement, centres, cloud.log_weights
        ))
        proposal_chol = batched_cholesky(update.posterior_cov)
        sampled = update.posterior.copy()
        sampled[:, index] += (proposal_chol @ rng.standard_normal((count, len(index), 1)))[:, :, 0]
        sampled = model.complete(wrap(sampled, ANGLES))

        likelihood = measurement.log_likelihood(measurement.z - measurement.predict(sampled))
        prior_chol = batched_cholesky(prior_cov)
        transition = gaussian_logpdf(wrap(sampled[:, index] - centres[:, index], angles), prior_chol)
        proposal = gaussian_logpdf(
            wrap(sampled[:, index] - update.posterior[:, index], angles), proposal_chol
        )
        prior_weights = np.exp(cloud.log_weights)
        z_hat = prior_weights @ update.z_hat
        spread = update.z_hat - z_hat
        z_cov = np.tensordot(prior_weights, update.z_cov, axes=1)
        z_cov = z_cov + (spread * prior_weights[:, None]).T @ spread
        score = nis(measurement.z - z_hat, z_cov)
        log_weights = normalise(cloud.log_weights + likelihood + transition - proposal)
        # The samples carry the posterior's spread; no noise is pending after a measurement.
        reset = embed(cloud.cov, np.zeros((len(index), len(index))), active)
        return _finish(sampled, log_weights, reset, active, score, self.resample_threshold, rng, reset)


def _proposal_measurement(measurement: Measurement, centres: np.ndarray, log_weights: np.ndarray) -> Measurement:
    """The Gaussian measurement the UKF proposal uses: with a heavy-tailed likelihood, each component's
    variance inflated by its outlier responsibility at the cloud's predicted residual (see
    ``Measurement.proposal_variances``), so that a range the mixture discounts does not drag every
    particle's proposal; the importance weights still use the exact mixture."""
    if measurement.outlier_probability <= 0.0:
        return measurement
    predicted = measurement.predict(centres)
    weights = np.exp(log_weights)
    z_hat = weights @ predicted
    spread = weights @ ((predicted - z_hat) ** 2)
    variances = measurement.proposal_variances(measurement.z - z_hat, spread)
    return replace(measurement, variances=variances, outlier_probability=0.0, outlier_variance=0.0)
