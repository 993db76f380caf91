"""Unscented particle filter (section 2.2.1, eqs. 8-18), vectorised over particles.

Each particle runs a UKF step (eqs. 9-14) whose posterior N(x_hat_i, P_i) is its proposal (eq. 15); a
sample is drawn from it and weighted by likelihood x transition / proposal (eq. 16); the estimate is the
weighted mean (eq. 17) and the cloud is resampled when the effective sample size is low (eq. 18).
The covariance a particle's next UKF starts from is shared: the mean of the particles' proposal
covariances (they differ only through the linearisation point, metres against satellite ranges of
20 000 km), which keeps the stored state small.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edgepos.core.motion.riss import ANGLES
from edgepos.core.particles.base import (
    Cloud,
    Measurement,
    ParticleModel,
    StepResult,
    batched_cholesky,
    diagonal_logpdf,
    embed,
    gaussian_logpdf,
    normalise,
    unscented_step,
    wrap,
)
from edgepos.core.particles.pf import _finish


@dataclass(frozen=True)
class UnscentedParticleFilter:
    """UKF proposal per particle; ``resample_threshold`` is the ESS fraction that triggers resampling."""

    resample_threshold: float = 0.5
    name = "upf"

    def step(
        self, cloud: Cloud, model: ParticleModel, dt: float, active: np.ndarray, measurement: Measurement | None,
        rng: np.random.Generator,
    ) -> StepResult:
        index = np.flatnonzero(active)
        count = len(cloud.particles)
        angles = ANGLES[index]
        if measurement is None:
            # No observation: the proposal is the prior; the shared covariance follows the UKF time update
            # of the weighted mean.
            weights = np.exp(cloud.log_weights)
            centre = (weights @ cloud.particles)[None, :]
            centre[0, ANGLES] = np.arctan2(weights @ np.sin(cloud.particles[:, ANGLES]), weights @ np.cos(cloud.particles[:, ANGLES]))
            step = unscented_step(centre, cloud.cov, model, dt, active, ANGLES, None)
            chol = batched_cholesky(model.process_noise(dt)[np.ix_(index, index)])
            particles = model.propagate(cloud.particles, dt)
            particles[:, index] += rng.standard_normal((count, len(index))) @ chol.T
            particles = model.complete(wrap(particles, ANGLES))
            shared = embed(cloud.cov, step.predicted_cov[0], active)
            return _finish(particles, cloud.log_weights, cloud.cov, active, None, self.resample_threshold, rng, shared)

        step = unscented_step(cloud.particles, None, model, dt, active, ANGLES, measurement)
        assert step.posterior is not None and step.posterior_cov is not None and step.z_hat is not None
        proposal_chol = batched_cholesky(step.posterior_cov)
        noise = rng.standard_normal((count, len(index)))
        particles = step.posterior.copy()
        particles[:, index] += np.einsum("nij,nj->ni", proposal_chol, noise)
        particles = model.complete(wrap(particles, ANGLES))

        likelihood = diagonal_logpdf(measurement.z - measurement.predict(particles), measurement.variances)
        transition_chol = batched_cholesky(model.process_noise(dt)[np.ix_(index, index)])
        transition = gaussian_logpdf(wrap(particles[:, index] - step.prior[:, index], angles), transition_chol)
        proposal = gaussian_logpdf(wrap(particles[:, index] - step.posterior[:, index], angles), proposal_chol)
        prior_weights = np.exp(cloud.log_weights)
        z_hat = prior_weights @ step.z_hat
        z_cov = np.einsum("n,nij->ij", prior_weights, step.z_cov)
        spread = step.z_hat - z_hat
        z_cov = z_cov + (spread * prior_weights[:, None]).T @ spread
        innovation = measurement.z - z_hat
        score = float(innovation @ np.linalg.solve(z_cov, innovation))
        log_weights = normalise(cloud.log_weights + likelihood + transition - proposal)
        shared = embed(cloud.cov, np.einsum("n,nij->ij", np.exp(log_weights), step.posterior_cov), active)
        return _finish(particles, log_weights, cloud.cov, active, score, self.resample_threshold, rng, shared)
