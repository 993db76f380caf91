"""Interacting multiple models (Blom & Bar-Shalom 1988) and the twice-interacting 2IMM (RSU + IMU
paper, eqs. 29-38), over motion models that use different state components.

The bank is held padded in the full 8-dim frame: means (B, 8) and covariances (B, 8, 8), zero where
a model lacks a component. Interaction mixes only the components every model carries (``common``);
a model's own extra components keep their conditional Gaussian given the common ones
(x_e + B (x_c' - x_c), B = P_ec P_cc^-1), so the mixed covariance stays positive definite. Outputs
are moment-matched over ``common``.

Transition matrix convention: ``transition[i, j]`` = P(model j at k | model i at k-1); rows sum to 1.
Model probabilities are handled in the log domain, so no likelihood underflows to zero.

2IMM: models in the priority set interact first (probabilities renormalised among themselves, eq. 30;
output combined, eqs. 31-32); that result then competes with the other models using the best
priority-set likelihood (eqs. 33-37); finally priority probabilities are scaled by the first-stage
share (eq. 38) so all probabilities sum to 1. The two output stages together equal one moment match
of every model with the eq. 38 probabilities, which is how the output is computed. With every model
in the priority set this is IMM.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from edgepos.core import layout
from edgepos.core.errors import ConfigurationError, NumericalError
from edgepos.core.filters.base import GaussianFilter, UpdateResult
from edgepos.core.motion.base import MotionModel
from edgepos.core.numerics import FloatArray, require_finite, weighted_mean, wrap_rows

_TINY = 1e-300


@dataclass(frozen=True)
class Gaussian:
    """A mean and covariance over the full-state ``components`` listed, in that order."""

    components: tuple[int, ...]
    mean: np.ndarray
    cov: np.ndarray


@dataclass(frozen=True)
class Prediction:
    """Every model's prior at the new time (padded), predicted probabilities c_j, fused prior."""

    means: np.ndarray
    covs: np.ndarray
    predicted_probabilities: np.ndarray
    output: Gaussian


@dataclass(frozen=True)
class StepResult:
    """Posteriors (padded), model probabilities, the fused output and per-model innovation stats."""

    means: np.ndarray
    covs: np.ndarray
    probabilities: np.ndarray
    output: Gaussian
    log_likelihoods: np.ndarray
    nis: np.ndarray


# Trusted constructors: the compiled stepper (``core.compiled``) builds a Gaussian and a
# StepResult every epoch from arrays it made itself. A frozen dataclass's generated ``__init__`` sets
# each field through ``object.__setattr__``; filling the instance's ``__dict__`` gives the same object
# (equal, pickled alike) for about a third of the time.
def new_gaussian(components: tuple[int, ...], mean: np.ndarray, cov: np.ndarray) -> Gaussian:
    """``Gaussian(components, mean, cov)`` without the frozen ``__init__``."""
    gaussian = object.__new__(Gaussian)
    gaussian.__dict__.update(components=components, mean=mean, cov=cov)
    return gaussian


def new_step_result(
    means: np.ndarray,
    covs: np.ndarray,
    probabilities: np.ndarray,
    output: Gaussian,
    log_likelihoods: np.ndarray,
    nis: np.ndarray,
) -> StepResult:
    """``StepResult(...)`` without the frozen ``__init__``."""
    result = object.__new__(StepResult)
    result.__dict__.update(
        means=means,
        covs=covs,
        probabilities=probabilities,
        output=output,
        log_likelihoods=log_likelihoods,
        nis=nis,
    )
    return result


def _index(components: tuple[int, ...]) -> slice | list[int]:
    """A slice when the components are contiguous (indexing then returns views), else a list."""
    if components == tuple(range(components[0], components[-1] + 1)):
        return slice(components[0], components[-1] + 1)
    return list(components)


#: A sub-matrix index: two slices (indexing returns a view) or np.ix_'s open mesh.
_Block = tuple[slice, slice] | tuple[npt.NDArray[np.intp], ...]


def _block(rows: slice | list[int], cols: slice | list[int]) -> _Block:
    """Index of the sub-matrix rows x cols."""
    if isinstance(rows, slice) and isinstance(cols, slice):
        return rows, cols
    return np.ix_(np.arange(8)[rows], np.arange(8)[cols])


class _ExtraBlocks:
    """Index helpers for a model that carries components beyond the common ones."""

    def __init__(self, model: int, common: tuple[int, ...], extra: tuple[int, ...]) -> None:
        self.model = model
        self.common = _index(common)
        self.extra = _index(extra)
        self.cc = _block(self.common, self.common)
        self.ec = _block(self.extra, self.common)
        self.ce = _block(self.common, self.extra)
        self.ee = _block(self.extra, self.extra)


class Correction(ABC):
    """How a bank's priors become posteriors for one epoch (see ``core.updates``)."""

    @abstractmethod
    def apply(
        self, filt: GaussianFilter, means: np.ndarray, covs: np.ndarray, active: np.ndarray
    ) -> UpdateResult:
        """Posteriors of the padded priors given this epoch's measurements."""


class InteractingMultipleModel:
    """A bank of one filter type over several motion models; one model is plain filtering."""

    def __init__(
        self,
        models: Sequence[MotionModel],
        filt: GaussianFilter,
        transition: np.ndarray,
        priority: Sequence[int] | None = None,
    ) -> None:
        if not models:
            raise ConfigurationError("an IMM needs at least one motion model")
        self.models = tuple(models)
        self.filter = filt
        count = len(self.models)
        self.transition = np.asarray(transition, dtype=float)
        if self.transition.shape != (count, count):
            raise ConfigurationError(f"transition matrix must be {count}x{count}")
        if np.any(self.transition < 0.0) or not np.allclose(self.transition.sum(axis=1), 1.0, atol=1e-9):
            raise ConfigurationError("transition matrix rows must be probabilities summing to 1")
        self.common = tuple(sorted(set.intersection(*(set(m.components) for m in self.models))))
        if not {layout.XP, layout.YP} <= set(self.common):
            raise ConfigurationError("every model must carry position")
        self.common_mask = layout.angle_mask(self.common)
        self._common_has_angle = bool(self.common_mask.any())
        self._common = _index(self.common)
        rows, cols = _block(self._common, self._common)
        self._common_block = (slice(None), rows, cols)
        self.active = np.zeros((count, layout.FULL_DIM), dtype=bool)
        for j, model in enumerate(self.models):
            self.active[j, list(model.components)] = True
        self._extras = [
            _ExtraBlocks(j, self.common, tuple(c for c in m.components if c not in self.common))
            for j, m in enumerate(self.models)
            if len(m.components) > len(self.common)
        ]
        if priority is None or len(set(priority)) == count:
            self.priority = np.arange(count)
        else:
            self.priority = np.array(sorted({int(i) for i in priority}), dtype=int)
            if self.priority.size < 1 or self.priority.min() < 0 or self.priority.max() >= count:
                raise ConfigurationError("priority set must name models of the bank")
        self.others = np.array([i for i in range(count) if i not in set(self.priority.tolist())], dtype=int)

    @property
    def is_two_stage(self) -> bool:
        return self.others.size > 0

    def initial(self, mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The padded bank that gives each model its slice of a full 8-dim Gaussian."""
        means = np.where(self.active, mean, 0.0)
        covs = np.where(self.active[:, :, None] & self.active[:, None, :], cov, 0.0)
        return means, covs

    # -- mixtures over the common components --------------------------------------------------
    def _moments(
        self, weights: np.ndarray, means: np.ndarray, covs: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Moment-matched mean and covariance of a Gaussian mixture (common components only)."""
        if self._common_has_angle:
            mean = weighted_mean(means, weights, self.common_mask)
            spread = wrap_rows(means - mean, self.common_mask)
        else:
            mean = weights @ means
            spread = means - mean
        size = means.shape[1]
        cov = (weights @ covs.reshape(len(weights), -1)).reshape(size, size) + (spread.T * weights) @ spread
        return mean, 0.5 * (cov + cov.T)

    def combine(self, means: np.ndarray, covs: np.ndarray, probabilities: np.ndarray) -> Gaussian:
        """The fused estimate of the bank over the common components."""
        return Gaussian(
            self.common, *self._moments(probabilities, means[:, self._common], covs[self._common_block])
        )

    def mix(
        self, means: np.ndarray, covs: np.ndarray, probabilities: np.ndarray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Interaction (eqs. 11-14): every model's mixed initial condition, and c_j."""
        joint = self.transition * probabilities[:, None]  # P(model i before, model j now)
        predicted = joint.sum(axis=0)
        vanished = predicted < _TINY
        if vanished.any():  # no probability flows into j: it keeps its own estimate
            joint[:, vanished] = np.eye(len(self.models))[:, vanished]
            predicted = np.where(vanished, _TINY, predicted)
        weights = joint / joint.sum(axis=0)  # weights[i, j] = mu_{i|j}
        common_means = means[:, self._common]
        common_covs = covs[self._common_block]
        count, size = common_means.shape
        if self._common_has_angle:
            mixed = np.stack(
                [weighted_mean(common_means, weights[:, j], self.common_mask) for j in range(count)]
            )
            spread = wrap_rows(common_means[None, :, :] - mixed[:, None, :], self.common_mask)  # (j, i, c)
        else:
            mixed = weights.T @ common_means
            spread = common_means[None, :, :] - mixed[:, None, :]
        weighted_spread = spread * weights.T[:, :, None]
        mixed_covs = (weights.T @ common_covs.reshape(count, -1)).reshape(count, size, size)
        mixed_covs += weighted_spread.transpose(0, 2, 1) @ spread
        new_means = means.copy()
        new_covs = covs.copy()
        new_means[:, self._common] = mixed
        new_covs[self._common_block] = mixed_covs
        for blocks in self._extras:
            j = blocks.model
            self._carry_extras(blocks, means[j], covs[j], new_means[j], new_covs[j])
        return new_means, 0.5 * (new_covs + new_covs.transpose(0, 2, 1)), predicted / predicted.sum()

    def _carry_extras(
        self,
        blocks: _ExtraBlocks,
        old_mean: FloatArray,
        old_cov: FloatArray,
        new_mean: FloatArray,
        new_cov: FloatArray,
    ) -> None:
        """A model's extra components follow their conditional given its re-mixed common block."""
        own_cc = old_cov[blocks.cc]
        own_ec = old_cov[blocks.ec]
        try:
            regression = np.linalg.solve(own_cc, own_ec.T).T  # B = P_ec P_cc^-1
        except np.linalg.LinAlgError:
            raise NumericalError("common-component covariance is singular during interaction") from None
        shift = wrap_rows(new_mean[blocks.common] - old_mean[blocks.common], self.common_mask)
        new_mean[blocks.extra] = old_mean[blocks.extra] + regression @ shift
        wrap_rows(new_mean, layout.FULL_ANGLE_MASK)
        cross = regression @ new_cov[blocks.cc]
        new_cov[blocks.ec] = cross
        new_cov[blocks.ce] = cross.T
        new_cov[blocks.ee] = old_cov[blocks.ee] - regression @ own_ec.T + cross @ regression.T

    # -- one epoch ---------------------------------------------------------------------------
    def predict(
        self, means: np.ndarray, covs: np.ndarray, probabilities: np.ndarray, dt: float | None
    ) -> Prediction:
        """Interaction, then each model's prediction over ``dt`` (none when dt is None or 0)."""
        mixed_means, mixed_covs, predicted = self.mix(means, covs, probabilities)
        if dt:
            mixed_means, mixed_covs = self.filter.predict_bank(mixed_means, mixed_covs, self.models, dt)
        return Prediction(
            mixed_means, mixed_covs, predicted, self.combine(mixed_means, mixed_covs, predicted)
        )

    def coast(self, prediction: Prediction) -> StepResult:
        """An epoch without usable measurements: priors stand, probabilities are c_j."""
        count = len(self.models)
        return StepResult(
            prediction.means,
            prediction.covs,
            prediction.predicted_probabilities,
            prediction.output,
            np.zeros(count),
            np.full(count, np.nan),
        )

    def correct(self, prediction: Prediction, correction: Correction) -> StepResult:
        """Every model's update at once, then model probabilities and the output (IMM or 2IMM)."""
        result = correction.apply(self.filter, prediction.means, prediction.covs, self.active)
        log_likelihoods = result.log_likelihood
        require_finite("model likelihoods", log_likelihoods)
        log_predicted = np.log(np.maximum(prediction.predicted_probabilities, _TINY))
        if self.is_two_stage:
            probabilities = self._two_stage_probabilities(log_likelihoods, log_predicted)
        else:
            probabilities = _softmax(log_likelihoods + log_predicted)
        output = self.combine(result.means, result.covs, probabilities)
        return StepResult(result.means, result.covs, probabilities, output, log_likelihoods, result.nis)

    def _two_stage_probabilities(self, log_likelihoods: np.ndarray, log_predicted: np.ndarray) -> np.ndarray:
        """2IMM model probabilities (eqs. 30 and 33-35, combined by eq. 38).

        The two output interactions (eqs. 31-32, then 36-37) moment-match a mixture of mixtures,
        which by the law of total variance is the single moment match of all models weighted by
        these final probabilities; :meth:`combine` does that in one step.
        """
        first, second = self.priority, self.others
        first_probs = _softmax(log_likelihoods[first] + log_predicted[first])  # eq. 30
        best_first = log_likelihoods[first].max()  # eq. 33
        log_first_mass = np.log(np.sum(np.exp(log_predicted[first])))
        second_stage = _softmax(
            np.concatenate([[best_first + log_first_mass], log_likelihoods[second] + log_predicted[second]])
        )  # eqs. 34-35: [mu_0, mu_{n+1..N}]
        probabilities = np.empty(len(self.models))
        probabilities[first] = first_probs * second_stage[0]  # eq. 38
        probabilities[second] = second_stage[1:]
        return probabilities


def _softmax(log_weights: np.ndarray) -> np.ndarray:
    """Probabilities proportional to exp(log_weights); NumericalError when they cannot be normalised
    (a NaN or infinite log weight: the largest shifted weight is then not exactly 1)."""
    top = log_weights.max()
    if not np.isfinite(top):
        raise NumericalError("model log-probabilities are not finite")
    shifted = np.exp(log_weights - top)
    total = shifted.sum()
    if not (np.isfinite(total) and total >= 1.0):
        raise NumericalError("model probabilities cannot be normalised")
    probabilities: FloatArray = shifted / total
    return probabilities
