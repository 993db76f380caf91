"""The filter contract: predict one model's Gaussian; update a *bank* of Gaussians at once.

Prediction works on a motion model's sub-state (its ``components``). Updates work on a batch of B
Gaussians laid out in the full 8-dim frame (``core.layout``), each with a mask of the components its
model carries; inactive entries are zero in the mean and covariance. Measurement models see full-state
rows, so a component a model lacks reads as zero (a CV model predicts zero yaw rate). Batching every
model of an IMM into one update replaces per-model small-matrix calls by one call on a stack, which
is where a Python filter spends its time.

All filters share one Gaussian correction (:func:`kalman_correct`), fed with the predicted
measurement, its covariance S and the state-measurement cross covariance C that each filter
computes its own way.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from edgepos.core import layout
from edgepos.core.errors import NumericalError
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion.base import MotionModel, padded_linear_step
from edgepos.core.numerics import require_finite, wrap_angle
from edgepos.core.parameters import ParameterSpec

_LOG_TWO_PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class UpdateResult:
    """Posteriors of a batch (B, 8) / (B, 8, 8) and each one's innovation statistics (B,)."""

    means: np.ndarray
    covs: np.ndarray
    nis: np.ndarray
    log_likelihood: np.ndarray


class GaussianFilter(ABC):
    """Predict a Gaussian with a motion model; update a bank of Gaussians with a measurement."""

    name: ClassVar[str]
    #: The constructor's parameters a client may set by name, with the bounds the service accepts.
    parameters: ClassVar[tuple[ParameterSpec, ...]] = ()

    @abstractmethod
    def predict(
        self, mean: np.ndarray, cov: np.ndarray, motion: MotionModel, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Propagate one sub-state (mean, cov) over ``dt`` seconds with ``motion``."""

    def predict_bank(
        self, means: np.ndarray, covs: np.ndarray, models: tuple[MotionModel, ...], dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predict every model of a padded bank over ``dt``; returns new (means, covs).

        The whole bank is advanced by one stacked F P F^T + Q, exact for models linear in the state
        (nonlinear ones carry the identity there); models that are not linear are then predicted by
        :meth:`predict` and written over their slot.
        """
        transitions, noises = padded_linear_step(models, dt)
        if any(model.state_dependent_noise for model in models):
            noises = noises.copy()
            for j, model in enumerate(models):
                if model.state_dependent_noise:
                    block = np.ix_(model.components, model.components)
                    noises[j][block] = model.noise_covariance(means[j, list(model.components)], dt)
        new_covs = transitions @ covs @ transitions.transpose(0, 2, 1) + noises
        new_covs = 0.5 * (new_covs + new_covs.transpose(0, 2, 1))
        new_means = (transitions @ means[:, :, None])[:, :, 0]
        for j, model in enumerate(models):
            if not model.linear:
                idx = _index(model.components)
                own = (idx, idx) if isinstance(idx, slice) else np.ix_(idx, idx)
                new_means[j, idx], new_covs[j][own] = self.predict(means[j, idx], covs[j][own], model, dt)
        new_means[:, layout.PHI] = wrap_angle(new_means[:, layout.PHI])
        require_finite("predicted state", new_means, new_covs)
        return new_means, new_covs

    @abstractmethod
    def measurement_moments(
        self, means: np.ndarray, covs: np.ndarray, active: np.ndarray, measurement: MeasurementModel
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted measurements (B, p), their covariances S with R (B, p, p), cross covariances C (B, 8, p)."""

    def params(self) -> dict[str, Any]:
        """Tuning parameters, enough to rebuild the filter with ``cls(**params)``."""
        return {}

    def update(
        self,
        means: np.ndarray,
        covs: np.ndarray,
        active: np.ndarray,
        measurement: MeasurementModel,
        observed: np.ndarray,
    ) -> UpdateResult:
        """Condition every Gaussian of the batch on ``observed`` = h(x) + v."""
        predicted, innovation_cov, cross_cov = self.measurement_moments(means, covs, active, measurement)
        residuals = measurement.residual(observed, predicted)
        return kalman_correct(means, covs, residuals, innovation_cov, cross_cov)

    def update_one(
        self,
        mean: np.ndarray,
        cov: np.ndarray,
        components: tuple[int, ...],
        measurement: MeasurementModel,
        observed: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Update a single sub-state Gaussian: (mean, cov, NIS, log-likelihood)."""
        means, covs, active = embed_bank([(mean, cov)], [components])
        result = self.update(means, covs, active, measurement, observed)
        idx = list(components)
        return (
            result.means[0, idx],
            result.covs[0][np.ix_(idx, idx)],
            float(result.nis[0]),
            float(result.log_likelihood[0]),
        )


def _index(components: tuple[int, ...]) -> slice | list[int]:
    """A slice when the components are contiguous (indexing then gives views), else a list."""
    if components == tuple(range(components[0], components[-1] + 1)):
        return slice(components[0], components[-1] + 1)
    return list(components)


def embed_bank(
    gaussians: list[tuple[np.ndarray, np.ndarray]], components: list[tuple[int, ...]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lay sub-state Gaussians out as a padded bank: means (B, 8), covs (B, 8, 8), active (B, 8)."""
    count = len(gaussians)
    means = np.zeros((count, layout.FULL_DIM))
    covs = np.zeros((count, layout.FULL_DIM, layout.FULL_DIM))
    active = np.zeros((count, layout.FULL_DIM), dtype=bool)
    for b, ((mean, cov), comps) in enumerate(zip(gaussians, components)):
        idx = list(comps)
        means[b, idx] = mean
        covs[b][np.ix_(idx, idx)] = cov
        active[b, idx] = True
    return means, covs, active


def kalman_correct(
    means: np.ndarray,
    covs: np.ndarray,
    residuals: np.ndarray,
    innovation_cov: np.ndarray,
    cross_cov: np.ndarray,
) -> UpdateResult:
    """The Kalman correction of a batch through the Cholesky factor L of each S.

    With U = L^-1 C^T and e = L^-1 r: x+ = x + U^T e, P+ = P - U^T U (= P - K S K^T),
    NIS = e^T e and log|S| = 2 sum(log diag L). No explicit inverse; one batched solve.
    """
    try:
        chol = np.linalg.cholesky(innovation_cov)
    except np.linalg.LinAlgError:
        raise NumericalError("innovation covariance is not positive definite") from None
    whitened = np.linalg.solve(
        chol, np.concatenate([cross_cov.transpose(0, 2, 1), residuals[:, :, None]], axis=2)
    )
    gain_factor, whitened_residual = whitened[:, :, :-1], whitened[:, :, -1:]
    new_means = means + (gain_factor.transpose(0, 2, 1) @ whitened_residual)[:, :, 0]
    new_means[:, layout.PHI] = wrap_angle(new_means[:, layout.PHI])
    new_covs = covs - gain_factor.transpose(0, 2, 1) @ gain_factor
    new_covs = 0.5 * (new_covs + new_covs.transpose(0, 2, 1))
    nis = (whitened_residual * whitened_residual).sum(axis=(1, 2))
    log_det = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
    log_likelihood = -0.5 * (nis + log_det + residuals.shape[1] * _LOG_TWO_PI)
    require_finite("updated state", new_means, new_covs, log_likelihood)
    return UpdateResult(new_means, new_covs, nis, log_likelihood)
