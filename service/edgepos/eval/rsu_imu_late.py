"""The RSU + IMU evaluation's extra columns: smoothing, and late measurements.

Per run and algorithm, beside the filtered estimate of the run processed in time order:

* **smoothed**: the pipeline's fixed-lag smoother (``Pipeline.smooth`` with ``lag_s``), each epoch's
  estimate from the data up to ``lag_s`` after it: what the track endpoint shows for the oldest point of
  a window of that length;
* **late**: the run delivered as a vehicle would send it over a link where a fraction of the RSU
  measurements arrive late (``sim.delivery``), in batches of ``batch_epochs`` epochs, through the lag
  window; the error of the *last fix received* for each epoch (a revised fix replaces the earlier one);
* **dropped**: the same delivery with every measurement that missed its epoch's batch dropped, as a
  client without a lag window would have to.

Errors are kept as per-epoch sums of squares, like the filtered ones, so runs add up in any order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.core.observations import Observation
from edgepos.pipelines.base import Environment, Fix, InitialState, Pipeline
from edgepos.sim.delivery import LateDelivery, arrival_batches, arrival_times


@dataclass(frozen=True)
class LateSettings:
    """What the extra columns need: the smoother's lag (None: no smoothing column) and the late delivery
    (None: no late columns)."""

    smooth_lag_s: float | None = None
    delivery: LateDelivery | None = None
    batch_epochs: int = 1


def squared_errors(fixes: Sequence[Fix], truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-epoch squared position and velocity errors of one fix per epoch against ``truth`` (K, 4):
    x, y, vx, vy."""
    estimates = np.array([(fix.x, fix.y, fix.vx, fix.vy) for fix in fixes], dtype=float)
    pos_sq = (estimates[:, 0] - truth[:, 0]) ** 2 + (estimates[:, 1] - truth[:, 1]) ** 2
    vel_sq = (estimates[:, 2] - truth[:, 2]) ** 2 + (estimates[:, 3] - truth[:, 3]) ** 2
    return pos_sq, vel_sq


def last_fix_per_epoch(
    pipeline: Pipeline,
    state: bytes,
    batches: Sequence[Sequence[Observation]],
    environment: Environment,
    epoch_times: Sequence[float],
) -> list[Fix]:
    """Send ``batches`` in order and keep the last fix received for each epoch of ``epoch_times``; an epoch
    that never got a fix (all its measurements dropped) gets none (ValueError)."""
    latest: dict[float, Fix] = {}
    for batch in batches:
        fixes, state = pipeline.process(state, list(batch), environment)
        for fix in fixes:
            latest[fix.t] = fix
    missing = [t for t in epoch_times if t not in latest]
    if missing:
        raise ValueError(f"{len(missing)} epoch(s) got no fix, the first at t={missing[0]}")
    return [latest[t] for t in epoch_times]


def late_columns(
    pipeline: Pipeline,
    options: dict[str, object],
    initial: InitialState,
    observations: Sequence[Observation],
    environment: Environment,
    truth: np.ndarray,
    settings: LateSettings,
    rng: np.random.Generator,
) -> dict[str, np.ndarray]:
    """The extra per-epoch squared errors of one run: ``smooth_pos``/``smooth_vel`` and
    ``late_pos``/``late_vel``/``drop_pos``/``drop_vel`` as the settings ask."""
    out: dict[str, np.ndarray] = {}
    epoch_times = sorted({o.t for o in observations})
    if settings.smooth_lag_s is not None and pipeline.smoother:
        smoothed = pipeline.smooth(
            pipeline.create(options, initial), observations, environment, settings.smooth_lag_s
        )
        out["smooth_pos"], out["smooth_vel"] = squared_errors(smoothed, truth)
    if settings.delivery is not None:
        arrivals = arrival_times(observations, settings.delivery, rng)
        for name, drop in (("late", False), ("drop", True)):
            batches = arrival_batches(observations, arrivals, settings.batch_epochs, drop_late=drop)
            fixes = last_fix_per_epoch(
                pipeline, pipeline.create(options, initial), batches, environment, epoch_times
            )
            out[f"{name}_pos"], out[f"{name}_vel"] = squared_errors(fixes, truth)
    return out
