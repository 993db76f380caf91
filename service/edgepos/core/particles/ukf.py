"""A single unscented Kalman filter on the same models: the cheap baseline (one particle, no sampling)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edgepos.core.motion.riss import ANGLES
from edgepos.core.particles.base import (
    Cloud,
    Measurement,
    ParticleModel,
    StepResult,
    embed,
    nis,
    unscented_step,
)


@dataclass(frozen=True)
class UnscentedKalmanFilter:
    """The UKF of eqs. 9-14 on its own; the cloud holds one particle: the mean, with its covariance."""

    name = "ukf"

    def step(
        self,
        cloud: Cloud,
        model: ParticleModel,
        dt: float,
        active: np.ndarray,
        measurement: Measurement | None,
        rng: np.random.Generator,
    ) -> StepResult:
        del rng  # deterministic
        step = unscented_step(cloud.particles[:1], cloud.cov, model, dt, active, ANGLES, measurement)
        if measurement is None or step.posterior is None or step.posterior_cov is None:
            mean, block, score = step.predicted[0], step.predicted_cov[0], None
        else:
            mean, block = step.posterior[0], step.posterior_cov[0]
            assert step.z_hat is not None and step.z_cov is not None
            score = nis(measurement.z - step.z_hat[0], step.z_cov[0])
        cov = embed(cloud.cov, block, active)
        return StepResult(Cloud(mean[None, :].copy(), np.zeros(1), cov), mean, cov, score, 1.0, False)
