"""Smoothed fixes of the rsu_imu pipeline: the batch filtered as ``process()`` filters it, then Kim's
IMM smoother backwards (``core.smoothing``), fixed interval or fixed lag.

The forward pass is ``rsu_imu._step`` itself, epoch by epoch, so the filtered fixes are process()'s
to the bit. What the smoother needs of it is every epoch's per-model posteriors and model
probabilities (the session after the step): Kim's smoother predicts each model's posterior through
every model again (``core.smoothing.bank_pair_predictions``, on the numpy reference filter and
models, which the compiled kernels equal to rounding), so nothing inside the step is recorded and
process() is untouched.

Segments: epochs before initialisation ("uninitialised") are passed through; an "initialised" epoch
(the first RSU fix, or a restart after ``max_gap``) opens a segment, smoothed on its own, since the
restart forgets what came before; "predicted" epochs (nothing measured) are ordinary steps.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from edgepos.core import layout
from edgepos.core.imm import InteractingMultipleModel
from edgepos.core.observations import Observation
from edgepos.core.smoothing import bank_pair_predictions, imm_smooth, lag_ends
from edgepos.pipelines.base import Environment, Fix, PipelineInputError, Problem, ensure_finite_fixes
from edgepos.pipelines.rsu_imu import _bank, _decode, _options_key, _SessionState, _step
from edgepos.pipelines.rsu_imu_batch import Batch, batch_epochs, read_batch
from edgepos.pipelines.rsu_imu_fix import epoch_fix


@dataclass
class FilteredRun:
    """The forward pass of a batch: process()'s fixes and, per epoch, the bank after the step
    (None before initialisation)."""

    fixes: list[Fix]
    means: list[np.ndarray | None]  # (models, 8) posteriors, padded
    covs: list[np.ndarray | None]  # (models, 8, 8)
    probabilities: list[np.ndarray | None]  # (models,)


def smooth(
    state: bytes, observations: Sequence[Observation], environment: Environment, lag_s: float | None = None
) -> list[Fix]:
    """``RsuImuPipeline.smooth``: one smoothed fix per epoch, in time order (see that method)."""
    if lag_s is not None and not (isinstance(lag_s, (int, float)) and math.isfinite(lag_s) and lag_s >= 0.0):
        raise PipelineInputError([Problem(None, "lag_s", "must be a finite number of seconds >= 0")])
    session = _decode(state)
    batch = read_batch(session.options, session.t, observations, environment)
    bank = _bank(_options_key(session.options))
    run = filter_run(session, bank, observations, batch)
    return smooth_run(run, session, bank, lag_s)


def filter_run(
    session: _SessionState,
    bank: InteractingMultipleModel,
    observations: Sequence[Observation],
    batch: Batch,
) -> FilteredRun:
    """Filter a validated batch from ``session`` (advanced in place) exactly as process() does,
    keeping each epoch's bank."""
    run = FilteredRun([], [], [], [])
    epochs = batch_epochs(observations, batch, session.options)
    for k in range(len(epochs)):
        fix = _step(session, bank, epochs.part(k), observations, batch)
        kept = fix.status != "uninitialised"
        run.fixes.append(fix)
        run.means.append(session.means.copy() if kept else None)
        run.covs.append(session.covs.copy() if kept else None)
        run.probabilities.append(session.probabilities.copy() if kept else None)
    ensure_finite_fixes(run.fixes)
    return run


def segments(fixes: Sequence[Fix]) -> list[range]:
    """The runs of epochs smoothed together: each starts at an "initialised" fix (or at the batch's
    first filtered one) and stops before the next start or "uninitialised" fix."""
    out: list[range] = []
    start = None
    for k, fix in enumerate(fixes):
        if fix.status == "uninitialised" or fix.status == "initialised":
            if start is not None:
                out.append(range(start, k))
            start = None if fix.status == "uninitialised" else k
        elif start is None:
            start = k
    if start is not None:
        out.append(range(start, len(fixes)))
    return out


def smooth_run(
    run: FilteredRun, session: _SessionState, bank: InteractingMultipleModel, lag_s: float | None
) -> list[Fix]:
    """The smoothed fixes of a forward run: segment by segment, fixed interval (``lag_s`` None) or
    with the data up to t + ``lag_s`` for each epoch."""
    smoothed = list(run.fixes)
    for segment in segments(run.fixes):
        times = np.array([run.fixes[k].t for k in segment])
        # a segment holds filtered epochs only, whose bank was kept (not None)
        means = np.stack(cast("list[np.ndarray]", [run.means[k] for k in segment]))
        covs = np.stack(cast("list[np.ndarray]", [run.covs[k] for k in segment]))
        probabilities = np.stack(cast("list[np.ndarray]", [run.probabilities[k] for k in segment]))
        pairs = bank_pair_predictions(bank, means, covs, np.diff(times))
        result = imm_smooth(
            means, covs, probabilities, bank.transition, *pairs,
            angle_mask=layout.FULL_ANGLE_MASK, ends=None if lag_s is None else lag_ends(times, lag_s),
        )  # fmt: skip
        for row, k in enumerate(segment):
            smoothed[k] = _smoothed_fix(
                run.fixes[k], session, bank, result.means[row], result.covs[row], result.probabilities[row]
            )
    return ensure_finite_fixes(smoothed)


def _smoothed_fix(
    filtered: Fix,
    session: _SessionState,
    bank: InteractingMultipleModel,
    means: np.ndarray,
    covs: np.ndarray,
    probabilities: np.ndarray,
) -> Fix:
    """The fix of a smoothed bank, built as the filter builds its own (moment match over the common
    components, yaw rate, covariances); t, status, NIS and measurements are the filtered fix's."""
    view = dataclasses.replace(session, means=means, covs=covs, probabilities=probabilities)
    output = bank.combine(means, covs, probabilities)
    fix = epoch_fix(filtered.t, filtered.status, output, view, bank, {}, filtered.nis, filtered.nis_dof)
    return dataclasses.replace(fix, measurements=list(filtered.measurements))
