"""Bootstrap particle filter (section 2.1): the prior is the proposal, the likelihood weighs, and the
cloud is resampled (systematic) when the effective sample size falls below a fraction of N."""

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
    effective_sample_size,
    embed,
    normalise,
    systematic_resample,
    weighted_moments,
    wrap,
)


@dataclass(frozen=True)
class ParticleFilter:
    """Prior-proposal particle filter; ``resample_threshold`` is the ESS fraction that triggers resampling."""

    resample_threshold: float = 0.5
    name = "pf"

    def step(
        self, cloud: Cloud, model: ParticleModel, dt: float, active: np.ndarray, measurement: Measurement | None,
        rng: np.random.Generator,
    ) -> StepResult:
        index = np.flatnonzero(active)
        count = len(cloud.particles)
        chol = batched_cholesky(model.process_noise(dt)[np.ix_(index, index)])
        particles = model.propagate(cloud.particles, dt)
        particles[:, index] += rng.standard_normal((count, len(index))) @ chol.T
        particles = model.complete(wrap(particles, ANGLES))
        log_weights = cloud.log_weights
        score = None
        if measurement is not None:
            predicted = measurement.predict(particles)
            prior_weights = np.exp(log_weights)
            z_hat = prior_weights @ predicted
            spread = predicted - z_hat
            z_cov = (spread * prior_weights[:, None]).T @ spread + np.diag(measurement.variances)
            innovation = measurement.z - z_hat
            score = float(innovation @ np.linalg.solve(z_cov, innovation))
            log_weights = normalise(log_weights + diagonal_logpdf(measurement.z - predicted, measurement.variances))
        return _finish(particles, log_weights, cloud.cov, active, score, self.resample_threshold, rng)


def _finish(
    particles: np.ndarray, log_weights: np.ndarray, previous_cov: np.ndarray, active: np.ndarray,
    score: float | None, threshold: float, rng: np.random.Generator, shared_cov: np.ndarray | None = None,
) -> StepResult:
    """Estimate from the weighted cloud (eq. 17), then resample when the ESS is low (eq. 18)."""
    weights = np.exp(log_weights)
    mean, spread = weighted_moments(particles, weights, ANGLES)
    index = np.flatnonzero(active)
    cov = embed(previous_cov, spread[np.ix_(index, index)], active)
    ess = effective_sample_size(log_weights)
    resampled = ess < threshold * len(particles)
    if resampled:
        particles = particles[systematic_resample(log_weights, rng)]
        log_weights = np.full(len(particles), -np.log(len(particles)))
    stored = cov if shared_cov is None else shared_cov
    return StepResult(Cloud(particles, log_weights, stored), mean, cov, score, ess, bool(resampled))
