"""Bootstrap particle filter (section 2.1): the prior is the proposal, the likelihood weighs, and the
cloud is resampled (systematic) when the effective sample size falls below a fraction of N.

Regularised, with progressive correction (see ``ParticleFilter._correct``): when the likelihood of some 20
pseudoranges is much sharper than the cloud (after initialisation, a reset clock, a gap), one weighting
leaves a single particle, and the RISS model's process noise over a 0.1 s step (centimetres) cannot spread
the copies again: the cloud collapses and stays wherever it was.
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
    effective_sample_size,
    embed,
    nis,
    normalise,
    regularised_resample,
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
        self,
        cloud: Cloud,
        model: ParticleModel,
        dt: float,
        active: np.ndarray,
        measurement: Measurement | None,
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
            score = nis(measurement.z - z_hat, z_cov)
            particles, log_weights = self._correct(particles, log_weights, model, active, measurement, rng)
        return _finish(particles, log_weights, cloud.cov, active, score, self.resample_threshold, rng)

    def _correct(
        self,
        particles: np.ndarray,
        log_weights: np.ndarray,
        model: ParticleModel,
        active: np.ndarray,
        measurement: Measurement,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Weigh by the likelihood with progressive correction (Oudjane & Musso 2000): the likelihood enters
        in powers alpha_1 + alpha_2 + ... = 1, each the largest that keeps the effective sample size at the
        resampling threshold, with a regularised resampling (kernel mixture) between stages. One stage
        when the likelihood is no sharper than the cloud; several when the cloud is wide against it (after
        initialisation, a new constellation or a gap), where a single weighting would leave one particle
        and the cloud could never spread again. The resampling between stages keeps the weighted cloud's
        mean and covariance (``regularised_resample``): plain resampling lost about 1 / ESS of the spread
        each time, and a drive has hundreds of stages."""
        count = len(particles)
        target = max(self.resample_threshold * count, 1.0)
        remaining = 1.0
        for stage in range(_MAX_STAGES):
            residual = measurement.z - measurement.predict(particles)
            log_likelihood = measurement.log_likelihood(residual)
            last = stage == _MAX_STAGES - 1
            alpha = remaining if last else _largest_power(log_weights, log_likelihood, remaining, target)
            log_weights = normalise(log_weights + alpha * log_likelihood)
            remaining -= alpha
            if remaining <= 1e-9:
                break
            particles = model.complete(regularised_resample(particles, log_weights, active, ANGLES, rng))
            log_weights = np.full(count, -np.log(count))
        return particles, log_weights


_MAX_STAGES = 8
"""Most likelihood stages of one progressive correction; the last takes what is left."""


def _largest_power(
    log_weights: np.ndarray, log_likelihood: np.ndarray, remaining: float, target: float
) -> float:
    """The largest alpha <= remaining with ESS(weights x likelihood^alpha) >= target (bisection; the ESS
    falls as alpha grows); at least 1 / 64 of what remains so that the stages end."""
    if effective_sample_size(normalise(log_weights + remaining * log_likelihood)) >= target:
        return remaining
    low, high = remaining / 64.0, remaining
    for _ in range(20):
        middle = 0.5 * (low + high)
        if effective_sample_size(normalise(log_weights + middle * log_likelihood)) >= target:
            low = middle
        else:
            high = middle
    return low


def _finish(
    particles: np.ndarray,
    log_weights: np.ndarray,
    previous_cov: np.ndarray,
    active: np.ndarray,
    score: float | None,
    threshold: float,
    rng: np.random.Generator,
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
    return StepResult(Cloud(particles, log_weights, cov), mean, cov, score, ess, bool(resampled))
