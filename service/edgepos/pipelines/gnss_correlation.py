"""The ``gnss_tight`` pipeline's treatment of time-correlated pseudorange errors (``error_correlation``):
the options as a model, and the factor that makes the fix's covariance honest about them. The formulas
are in gnss/error_correlation.py; why this design and what it measured in docs/gnss.md."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.measurements.gnss_noise_kernel import honesty_numbers
from edgepos.core.motion import riss as layout
from edgepos.gnss.error_correlation import ErrorCorrelation, averaged_variance, honest_factor
from edgepos.gnss.noise_level import NoiseLevel, epoch_scale
from edgepos.pipelines.gnss_integrity import jacobian

_POSITION = np.array([layout.NORTH, layout.EAST, layout.UP])
_HORIZONTAL = np.ix_(_POSITION[:2], _POSITION[:2])
"""The north-east block's index arrays (built once: ``np.ix_`` costs more than the indexing)."""


def model_of(options: Mapping[str, Any]) -> ErrorCorrelation | None:
    """The session's error model; None for white errors (also sessions stored before the option)."""
    if options.get("error_correlation", "white") != "gauss_markov":
        return None
    return ErrorCorrelation(
        float(options["code_error_tau_s"]), float(options["code_error_correlated_fraction"])
    )


@dataclass(frozen=True)
class Honesty:
    """The factor on the filter's position covariance that makes it the covariance of the fix's error
    under the correlated error model, the filter memory (epochs) it was computed for, and ``bound``, the
    north-east covariance a Gaussian update of the prediction's horizontal marginal with the epoch's own
    least-squares one would give, inv(inv(P_prior) + inv(P_ls)) (None when not computed). ``bound`` leaves
    out what the Dopplers and the prior's vertical and clock parts tell about the horizontal position, so
    it is somewhat larger than a Kalman update's posterior (on the recording's first half, flooring the
    UKF's covariance at it would take its mean NEES from 1.73 to 1.16): a conservative floor for the
    particle filter, whose covariance from a couple of hundred particles collapses when they are
    resampled (its mean NEES was 2.7 times the UKF's before any factor)."""

    factor: float = 1.0
    memory: float = 1.0
    bound: np.ndarray | None = None

    def floored(self, cov: np.ndarray) -> Honesty:
        """This honesty with its factor raised until the posterior ``cov``'s north-east block C is at
        least ``bound`` (times s, the smallest with s C >= bound: the largest eigenvalue of C^-1 bound)."""
        if self.bound is None:
            return self
        block = cov[_HORIZONTAL]
        try:
            ratio = float(np.max(np.linalg.eigvals(np.linalg.solve(block, self.bound)).real))
        except np.linalg.LinAlgError:
            return self
        if not math.isfinite(ratio) or ratio <= 1.0:
            return self
        return Honesty(self.factor * ratio, self.memory, self.bound)

    def times(self, level: float) -> Honesty:
        """This honesty with its factor times the noise ``level`` (the variance scale the errors showed)."""
        if level == 1.0:
            return self
        return Honesty(self.factor * level, self.memory, self.bound)

    def scale(self, cov: np.ndarray) -> np.ndarray:
        """``cov`` (state order) with its position rows and columns times sqrt(factor): the position block
        times the factor, its correlations with the rest kept."""
        if self.factor == 1.0:
            return cov
        scale = np.ones(cov.shape[0])
        scale[_POSITION] = np.sqrt(self.factor)
        out: np.ndarray = cov * scale[:, None] * scale[None, :]
        return out


def honesty(
    options: Mapping[str, Any],
    rows: np.ndarray,
    std: np.ndarray,
    smoothing: np.ndarray,
    count: np.ndarray,
    ranges: np.ndarray,
    systems: Sequence[str],
    predicted_cov: np.ndarray,
    dt: float,
) -> Honesty:
    """The epoch's :class:`Honesty` for the update ``rows`` of the epoch's pseudoranges with the filter's
    noise ``std``, carrier-smoothing factors ``smoothing`` (in ``std``) over ``count`` epochs (0: raw
    code), linearisation ``ranges`` (gnss_integrity.linearisation_ranges), constellations ``systems``, the
    prediction's covariance (state order) and the interval since the previous epoch. The filter weighs the
    rows as white with std ``std``; under the model a row's error variance is std^2 x (V_smoothed(n) /
    smoothing^2) x its memory factor (gnss/error_correlation.py: the smoothed code's own variance, then the
    average over the filter's memory M of correlated errors); the factor is the consider covariance's
    horizontal trace over the white one. 1 for white errors, and when the rows alone do not fix the
    position."""
    model = model_of(options)
    if model is None or rows.size == 0 or dt <= 0.0:
        return Honesty()
    std, smoothing, count = std[rows], smoothing[rows], count[rows]
    predicted_horizontal = predicted_cov[_HORIZONTAL]
    variance = std**2
    scale = variance / smoothing**2  # each row's raw-code variance as the filter's noise model has it

    def true_variance(memory: float) -> np.ndarray:
        value: np.ndarray = scale * averaged_variance(count, memory, model, dt)[0]
        return value

    h = jacobian(ranges[:, rows], [systems[r] for r in rows.tolist()])
    if compiled_enabled():
        if h.shape[0] <= h.shape[1] or float(np.trace(predicted_horizontal)) <= 0.0:
            return Honesty()  # honest_factor's None: the rows alone do not fix the position
        numbers = honesty_numbers(
            h, variance, scale, count, predicted_horizontal, model.tau_s, model.fraction, dt
        )
        if numbers is not None:  # the compiled form (None: the numpy form below decides)
            return Honesty(*numbers)
    result = honest_factor(h, variance, predicted_horizontal, true_variance)
    if result is None:
        return Honesty()
    factor, memory, own = result
    try:
        bound = np.linalg.inv(np.linalg.inv(predicted_horizontal) + np.linalg.inv(own))
    except np.linalg.LinAlgError:
        return Honesty(factor, memory)
    return Honesty(factor, memory, bound)


def adaptive(options: Mapping[str, Any]) -> bool:
    """Whether the session follows the noise level (``noise_level`` adaptive); sessions stored before the
    option keep the model's level."""
    return bool(options.get("noise_level", "model") == "adaptive")


def level_inputs(
    options: Mapping[str, Any],
    dt: float,
    rows: np.ndarray,
    std: np.ndarray,
    smoothing: np.ndarray,
    count: np.ndarray,
    ranges: np.ndarray,
    systems: Sequence[str],
    pseudorange: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Jacobian, prefit residuals, error variances) of the update ``rows`` as the noise level fits them:
    each row's variance as the session's model has it (the filter's std^2 for white errors; under
    error_correlation the smoothed code's own variance, (std / smoothing)^2 V_smoothed(n), so that the level
    and the correlation factor do not count the same thing twice)."""
    variance = std[rows] ** 2
    model = model_of(options)
    if model is not None and dt > 0.0:
        variance = variance / smoothing[rows] ** 2 * model.smoothed_variance(count[rows], dt)
    h = jacobian(ranges[:, rows], [systems[r] for r in rows.tolist()])
    return h, pseudorange[rows] - ranges[0, rows], variance


def corrected_reference(options: Mapping[str, Any]) -> float:
    """The level's reference for rows with a differential correction; sessions stored before the option
    keep the raw-code reference for them (as they did)."""
    return float(options.get("noise_level_reference_corrected", options["noise_level_reference"]))


def noise_level(
    options: Mapping[str, Any],
    level: NoiseLevel,
    t: float,
    dt: float,
    rows: np.ndarray,
    std: np.ndarray,
    smoothing: np.ndarray,
    count: np.ndarray,
    ranges: np.ndarray,
    systems: Sequence[str],
    pseudorange: np.ndarray,
    corrected: np.ndarray | None = None,
) -> NoiseLevel:
    """``level`` updated with the epoch's update ``rows`` (gnss/noise_level.py): their residuals after the
    epoch's own least-squares fit, standardised as :func:`level_inputs` says. ``level`` itself when the
    session does not adapt or the rows do not exceed the unknowns. The estimate is stored relative to the
    reference (its value where the model holds), so the memory's scale is the factor on the covariance.

    Rows with a differential correction (``corrected``, per row of the epoch; None without corrections)
    have their own reference, ``noise_level_reference_corrected``: their post-fit residuals are smaller
    than raw code's. The epoch's rows are a mix whose share changes from epoch to epoch (a satellite the
    base does not track, a stale correction), so the reference is applied per row, not to the epoch's
    estimate: each corrected row's variance is multiplied by the ratio of the two references, which makes
    every row's studentised square relative to its own kind's reference and the median one level, whatever
    the mix. Without corrected rows nothing changes (the same numbers as before the option)."""
    if not adaptive(options) or rows.size == 0:
        return level
    h, residual, variance = level_inputs(
        options, dt, rows, std, smoothing, count, ranges, systems, pseudorange
    )
    reference = float(options["noise_level_reference"])
    if corrected is not None:
        ratio = corrected_reference(options) / reference
        if ratio != 1.0 and corrected[rows].any():
            variance = variance * np.where(corrected[rows], ratio, 1.0)
    estimate, redundancy = epoch_scale(h, residual, variance)
    return level.updated(t, estimate / reference, redundancy, float(options["noise_level_time_constant_s"]))
