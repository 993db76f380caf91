"""Unscented particle filter (section 2.2.1, eqs. 8-18), vectorised over particles.

As in the paper, every particle is a Gaussian: a centre c_i and its own covariance P (one matrix shared by
all particles, since the RISS model's noise does not depend on the state and the particles lie metres
apart on orbits 20,000 km away). Between measurements each centre is propagated and P gets the UKF time
update (eq. 11) at the cloud's mean. At a measurement each particle's UKF update of N(c_i, P) (eqs. 12-14)
is its proposal q_i = N(x_hat_i, P_i) (eq. 15); a sample x_i ~ q_i is weighted by likelihood x prior /
proposal (eq. 16), the prior being the particle's own N(c_i, P). For a linear model that weight is the
predictive likelihood N(z; z_hat_i, S_i) whatever the sample (tested). The estimate is the weighted mean
(eq. 17); the cloud is resampled when the effective sample size is low (eq. 18).

What each particle keeps of its proposal: the paper keeps the sample x_i and the proposal covariance P_i
together, which counts the proposal's spread twice (once in the samples, once in P_i) and, with a
transition density of one 0.1 s step, gave one particle all the weight at every update. Here a particle
keeps its proposal mean plus a fraction ``spread_fraction`` f of the sample's deviation (sqrt(f) (x_i -
x_hat_i)) as its new centre and (1 - f) P_i as its own covariance, so the cloud stands for exactly the
proposals' mixture. f = 1 puts all the uncertainty in the spread of the particles (a regularised particle
filter with UKF proposals); f -> 0 carries it analytically, each particle a UKF, and the particles differ
only as far as the importance weights and resampling have made them. Measured on the urban drive (see
docs/gnss-simulation.md), f = 0.02 is the default: the more of the uncertainty the particles carry as
spread, the more the weights select the particles that follow reflected-signal biases, which persist for
tens of seconds in a street canyon.

The proposal is the Gaussian UKF update; a heavy-tailed likelihood (``Measurement.outlier_probability``)
enters the importance weights only.

The particles' UKF updates share one linearisation (``shared_linearisation``, the default): with one
covariance for all, their sigma points differ only by where they are centred, and over the metres between
particles the measurement function's curvature (range / 20,000 km) changes the deviations by micrometres.
So the sigma-point deviations, innovation covariance, gain and posterior covariance are computed once, at
the cloud's mean carried over the step (the time update's central sigma point), and each particle's
predicted measurement is h at its own centre plus the second-order sigma-point term: h at N + 2k + 1 states
instead of N (2k + 1), one (m, m) solve instead of N. The per-particle update stays as the reference it is
tested against (tests/core/test_core_upf_shared.py: the same particles to a millimetre, weights to 1 %,
estimate to 0.1 mm, on the pipeline's range models).

With the GNSS-only motion model the step runs in compiled loops (``upf_step_kernel``: the time update, the
shared update and the draws, then the weights, NIS and moments; ``upf_resample_kernel``: the resampling),
around the measurement's own prediction; the numpy step here stays their reference and runs wherever they
decline or the kernels are off (``EDGEPOS_NUMBA=0``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from edgepos.core.motion.riss import ANGLES
from edgepos.core.numerics import FloatArray
from edgepos.core.particles.base import (
    Cloud,
    Measurement,
    ParticleModel,
    StepResult,
    batched_cholesky,
    effective_sample_size,
    embed,
    gaussian_logpdf,
    nis,
    normalise,
    regularised_resample,
    shared_unscented_update,
    unscented_predict,
    unscented_update,
    weighted_moments,
    wrap,
)
from edgepos.core.particles.upf_kernel import log_weights as compiled_log_weights
from edgepos.core.particles.upf_resample_kernel import compiled_resample
from edgepos.core.particles.upf_step_kernel import Proposal, Weighed, compiled_proposal, compiled_weights


def predicted_own_covariance(cloud: Cloud, model: ParticleModel, dt: float, active: np.ndarray) -> np.ndarray:
    """The particles' own covariance carried over ``dt`` (k, k): the UKF time update of N(weighted mean,
    cloud.cov). The dynamics are nearly linear over a step and the particles close together, so one
    linearisation point serves every particle."""
    return _own_prediction(cloud, model, dt, active)[1]


def _own_prediction(
    cloud: Cloud, model: ParticleModel, dt: float, active: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The cloud's weighted mean carried over ``dt`` (D,), where the shared update linearises, and
    :func:`predicted_own_covariance`."""
    centre, _ = cloud.moments(ANGLES)
    moved, _, cov = unscented_predict(centre[None, :], cloud.cov, model, dt, active, ANGLES)
    own: FloatArray = cov[0]
    return model.complete(wrap(moved, ANGLES))[0], own


@dataclass(frozen=True)
class UnscentedParticleFilter:
    """UKF proposal per particle. ``resample_threshold``: the ESS fraction that triggers resampling;
    ``spread_fraction``: the fraction of each proposal's covariance the particles carry as their spread
    (the rest stays their own covariance); ``shared_linearisation``: the particles' UKF updates take their
    sigma-point deviations once, at the cloud's propagated mean (``base.shared_unscented_update``, the particles
    sharing one covariance and lying metres apart), instead of around each particle (False: the
    reference the shared one is tested against, about 20 times slower with 200 particles)."""

    resample_threshold: float = 0.5
    spread_fraction: float = 0.02
    shared_linearisation: bool = True
    name = "upf"

    def covariance(self, cloud: Cloud) -> np.ndarray:
        """The state covariance the cloud stands for: spread of the centres plus their own covariance."""
        _, spread = cloud.moments(ANGLES)
        total: FloatArray = spread + cloud.cov
        return total

    def step(
        self,
        cloud: Cloud,
        model: ParticleModel,
        dt: float,
        active: np.ndarray,
        measurement: Measurement | None,
        rng: np.random.Generator,
    ) -> StepResult:
        if measurement is not None and self.shared_linearisation:
            compiled = compiled_proposal(cloud, model, dt, active, measurement, rng, self.spread_fraction)
            if compiled is not None:
                return self._weigh(cloud, model, active, measurement, rng, compiled)
        reference, predicted_cov = _own_prediction(cloud, model, dt, active)
        centres = model.complete(wrap(model.propagate(cloud.particles, dt), ANGLES))
        if measurement is None:
            own = embed(cloud.cov, predicted_cov, active)
            mean, spread = weighted_moments(centres, cloud.weights, ANGLES)
            ess = effective_sample_size(cloud.log_weights)
            return StepResult(Cloud(centres, cloud.log_weights, own), mean, spread + own, None, ess, False)
        proposal = self._proposal(cloud, model, active, measurement, rng, centres, reference, predicted_cov)
        return self._weigh(cloud, model, active, measurement, rng, proposal)

    def _proposal(
        self,
        cloud: Cloud,
        model: ParticleModel,
        active: np.ndarray,
        measurement: Measurement,
        rng: np.random.Generator,
        centres: np.ndarray,
        reference: np.ndarray,
        predicted_cov: np.ndarray,
    ) -> Proposal:
        """Each particle's UKF update of N(centre, predicted_cov) (shared or per particle), a draw from it,
        and the particle kept: the numpy step (``upf_step_kernel`` is held to it)."""
        index = np.flatnonzero(active)
        count = len(cloud.particles)
        angles = ANGLES[index]
        gaussian = replace(measurement, outlier_probability=0.0, outlier_variance=0.0)
        if self.shared_linearisation:
            update = shared_unscented_update(
                centres, predicted_cov, model, active, ANGLES, gaussian, reference
            )
        else:
            update = unscented_update(centres, predicted_cov, model, active, ANGLES, gaussian)
        proposal_chol = batched_cholesky(update.posterior_cov)
        draws = rng.standard_normal((count, len(index), 1))
        if proposal_chol.ndim == 2:
            deviation = draws[:, :, 0] @ proposal_chol.T
        else:
            deviation = (proposal_chol @ draws)[:, :, 0]
        sampled = update.posterior.copy()
        sampled[:, index] += deviation
        sampled = model.complete(wrap(sampled, ANGLES))
        # Keep sqrt(f) of each sample's deviation as spread and (1 - f) of the proposal covariance as the
        # particles' own (``_weigh``): the cloud's mean and covariance are the weighted proposals' mixture.
        particles = update.posterior.copy()
        particles[:, index] += math.sqrt(self.spread_fraction) * deviation
        particles = model.complete(wrap(particles, ANGLES))
        return Proposal(
            centres,
            update.posterior_cov,
            proposal_chol,
            batched_cholesky(predicted_cov),
            update.z_hat,
            update.z_cov,
            sampled,
            particles,
            wrap(sampled[:, index] - centres[:, index], angles),
            wrap(sampled[:, index] - update.posterior[:, index], angles),
        )

    def _weigh(
        self,
        cloud: Cloud,
        model: ParticleModel,
        active: np.ndarray,
        measurement: Measurement,
        rng: np.random.Generator,
        proposal: Proposal,
    ) -> StepResult:
        """Importance weights of the samples (likelihood x prior / proposal), the new cloud and estimate,
        and resampling when the effective sample size is low."""
        count = len(cloud.particles)
        residual = measurement.z - measurement.predict(proposal.sampled)
        fraction = self.spread_fraction
        particles = proposal.particles
        weighed = compiled_weights(
            cloud.log_weights, measurement, residual, proposal, cloud.cov, active, fraction
        )
        if weighed is None:  # the reference: numpy, and particles with covariances of their own
            weighed = self._numpy_weights(cloud, measurement, residual, proposal, active)
        elif math.isnan(weighed.score):  # the kernel found no Cholesky factor: numpy's solve decides
            score = _innovation_score(measurement, cloud.weights, proposal.z_hat, proposal.z_cov)
            weighed = weighed._replace(score=score)
        log_weights, mean, spread, own = weighed.log_weights, weighed.mean, weighed.spread, weighed.own
        resampled = weighed.ess < self.resample_threshold * count
        if resampled:
            drawn = compiled_resample(particles, log_weights, mean, spread, active, ANGLES, rng)
            if drawn is None:  # the reference, and wherever the kernel declines
                drawn = regularised_resample(particles, log_weights, active, ANGLES, rng)
            particles = model.complete(drawn)
            log_weights = np.full(count, -math.log(count))
        new = Cloud(particles, log_weights, own)
        if not resampled:  # the next step and the pipeline's prediction start from these very moments
            new.remember_moments(ANGLES, mean, spread)
        return StepResult(new, mean, spread + own, weighed.score, weighed.ess, bool(resampled))

    def _numpy_weights(
        self,
        cloud: Cloud,
        measurement: Measurement,
        residual: np.ndarray,
        proposal: Proposal,
        active: np.ndarray,
    ) -> Weighed:
        """The importance weights (likelihood x prior / proposal), the innovation's NIS, the particles' own
        covariance and the new cloud's moments, in numpy (``upf_step_kernel.weigh_kernel`` is held to it)."""
        log_weights = compiled_log_weights(
            cloud.log_weights,
            measurement,
            residual,
            proposal.prior_deviation,
            proposal.prior_chol,
            proposal.proposal_deviation,
            proposal.proposal_chol,
        )
        if log_weights is None:
            likelihood = measurement.log_likelihood(residual)
            prior = gaussian_logpdf(proposal.prior_deviation, proposal.prior_chol)
            density = gaussian_logpdf(proposal.proposal_deviation, proposal.proposal_chol)
            log_weights = normalise(cloud.log_weights + likelihood + prior - density)
        score = _innovation_score(measurement, cloud.weights, proposal.z_hat, proposal.z_cov)
        weights = np.exp(log_weights)
        if proposal.posterior_cov.ndim == 2:
            posterior_cov = proposal.posterior_cov  # shared: the weighted average of one matrix
        else:
            posterior_cov = np.tensordot(weights, proposal.posterior_cov, axes=1)
        own = embed(cloud.cov, (1.0 - self.spread_fraction) * posterior_cov, active)
        mean, spread = weighted_moments(proposal.particles, weights, ANGLES)
        return Weighed(log_weights, score, own, mean, spread, effective_sample_size(log_weights))


def _innovation_score(
    measurement: Measurement, weights: np.ndarray, z_hat: np.ndarray, z_cov: np.ndarray
) -> float:
    """NIS of the measurement against the prior mixture's predicted measurement (the weights before the
    update)."""
    mean = weights @ z_hat
    spread = z_hat - mean
    shared = z_cov if z_cov.ndim == 2 else np.tensordot(weights, z_cov, axes=1)
    cov = shared + (spread * weights[:, None]).T @ spread
    return nis(measurement.z - mean, cov)
