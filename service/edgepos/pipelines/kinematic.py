"""What the kinematic pipelines share: batch checks, the dead-reckoning update, and the fix of a
[xp, xv, xa, yp, yv, ya] Gaussian."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from edgepos.core import layout
from edgepos.core.filters.base import GaussianFilter
from edgepos.core.measurements.base import MeasurementModel, Stacked
from edgepos.core.measurements.gyro import GyroYawRate
from edgepos.core.measurements.odometer import OdometerDistance
from edgepos.core.observations import GyroObservation, Observation, OdometerObservation
from edgepos.pipelines.base import (
    Fix,
    MeasurementUse,
    PipelineInputError,
    Problem,
    TrackPoint,
    is_finite_number,
)

KINEMATIC = layout.KINEMATIC
_TRACK_ORDER = [0, 3, 1, 4]  # [x, y, vx, vy] of the published track


def kinematic_fix(
    t: float, status: str, mean: np.ndarray, cov: np.ndarray, uses: list[MeasurementUse]
) -> Fix:
    """The fix of the kinematic state (mean (6,), cov (6, 6)) with its 4x4 [x, y, vx, vy] covariance,
    which is what the service publishes as the vehicle's track."""
    xp, xv, _, yp, yv, _ = (float(v) for v in mean)
    speed = math.hypot(xv, yv)
    return Fix(
        t=t,
        status=status,
        x=xp,
        y=yp,
        vx=xv,
        vy=yv,
        speed=speed,
        heading=math.atan2(yv, xv) if speed > 0 else None,
        position_cov=cov[np.ix_([0, 3], [0, 3])].tolist(),
        kinematic_cov=cov[np.ix_(_TRACK_ORDER, _TRACK_ORDER)].tolist(),
        state_components=tuple(layout.NAMES[c] for c in KINEMATIC),
        state=[float(v) for v in mean],
        state_cov=cov.tolist(),
        measurements=uses,
    )


def shared_point(t: float, mean: np.ndarray, cov: np.ndarray) -> TrackPoint:
    """The kinematic state (mean (6,), cov (6, 6)) as the track point a vehicle shares."""
    block = cov[np.ix_(_TRACK_ORDER, _TRACK_ORDER)]
    return TrackPoint(
        t,
        float(mean[0]),
        float(mean[3]),
        float(mean[1]),
        float(mean[4]),
        tuple(tuple(float(v) for v in row) for row in block),
    )


def check_batch(
    pipeline: str, kinds: set[str], last_t: float | None, observations: Sequence[Observation]
) -> None:
    """Refuse, listing every problem: kinds the pipeline does not take, non-finite times, times
    going back (before the session's last epoch or within the batch), negative odometer distances."""
    problems: list[Problem] = []
    previous = last_t
    for index, obs in enumerate(observations):
        if obs.kind not in kinds:
            problems.append(
                Problem(index, "kind", f"pipeline {pipeline} takes {sorted(kinds)}, not {obs.kind!r}")
            )
            continue
        if not is_finite_number(obs.t):
            problems.append(Problem(index, "t", "must be a finite number"))
            continue
        if previous is not None and obs.t < previous:
            problems.append(
                Problem(index, "t", f"time {obs.t} goes back before {previous} (observations in time order)")
            )
        previous = obs.t if previous is None else max(previous, obs.t)
        if isinstance(obs, OdometerObservation) and obs.distance is not None and obs.distance < 0.0:
            problems.append(Problem(index, "distance", "must be >= 0"))
    if problems:
        raise PipelineInputError(problems)


@dataclass(frozen=True)
class DeadReckoning:
    """The outcome of a dead-reckoning update: the new Gaussian, whether anything was used, and the
    time of the latest odometer distance reading (which starts the next reading's interval)."""

    mean: np.ndarray
    cov: np.ndarray
    used: bool
    odometer_t: float | None


def dead_reckoning_update(
    filt: GaussianFilter,
    mean: np.ndarray,
    cov: np.ndarray,
    epoch: Sequence[int],
    observations: Sequence[Observation],
    uses: dict[int, MeasurementUse],
    odometer_t: float | None,
    gyro_std: float,
    odometer_std: float,
) -> DeadReckoning:
    """The epoch's gyro yaw rate and odometer distance (or speed) as one stacked update of (mean, cov)
    (the federated paper's eq. 8). A distance needs the previous distance reading's time for its
    interval; the first one is reported unused. Extra readings at the same time are reported unused."""
    t = observations[epoch[0]].t
    parts: list[MeasurementModel] = []
    values: list[float] = []
    gyros = [i for i in epoch if isinstance(observations[i], GyroObservation)]
    odos = [i for i in epoch if isinstance(observations[i], OdometerObservation)]
    for i in gyros[1:]:
        uses[i] = MeasurementUse(i, "gyro", False, "another gyro reading at the same time was used")
    for i in odos[1:]:
        uses[i] = MeasurementUse(i, "odometer", False, "another odometer reading at the same time was used")
    # gyros and odos index observations their isinstance filters established (cast: free at run time)
    if gyros:
        parts.append(GyroYawRate(gyro_std))
        values.append(cast(GyroObservation, observations[gyros[0]]).yaw_rate)
        uses[gyros[0]] = MeasurementUse(gyros[0], "gyro", True)
    if odos:
        obs = cast(OdometerObservation, observations[odos[0]])
        if obs.speed is not None:
            parts.append(OdometerDistance(odometer_std, 1.0))
            values.append(obs.speed)
            uses[odos[0]] = MeasurementUse(odos[0], "odometer", True)
        elif odometer_t is None or t <= odometer_t:
            uses[odos[0]] = MeasurementUse(
                odos[0], "odometer", False, "first distance reading: no previous reading starts its interval"
            )
        else:
            parts.append(OdometerDistance(odometer_std, t - odometer_t))
            values.append(cast(float, obs.distance))  # speed is None: exactly one of the two is set
            uses[odos[0]] = MeasurementUse(odos[0], "odometer", True)
        if obs.distance is not None:
            odometer_t = t
    if not parts:
        return DeadReckoning(mean, cov, False, odometer_t)
    model = parts[0] if len(parts) == 1 else Stacked(parts)
    mean, cov, _, _ = filt.update_one(mean, cov, KINEMATIC, model, np.array(values))
    return DeadReckoning(mean, cov, True, odometer_t)


HEADING_SIGMAS = 5.0
"""Dead reckoning starts once the speed is this many standard deviations of the velocity: the direction
of travel is then known to about 1/5 rad (11 deg) or better. Chosen on the V2V ring with the papers'
options and covariance intersection, no fault, 100 runs each of seeds 300 and 400 (seeds the reported
tables do not use; docs/v2v.md "When dead reckoning starts"): 3 sigma let a noisy early velocity pass,
the gyro and odometer then held a heading 20-30 deg off (22 and 92 misleading epochs of 40,000 on seed
400, UKF and GPS/DR); 4 to 7 sigma gave none, with the lowest RMSE at 5-6."""


def heading_known(mean: np.ndarray, cov: np.ndarray) -> bool:
    """Whether the direction of travel is established: speed at least HEADING_SIGMAS sigma of the velocity.

    Yaw rate and distance say nothing about the heading; linearised at a velocity near zero, or in
    the wrong direction, they pin the speed along an arbitrary axis and hold it there (measured: a
    vehicle started at rest with its fixes heading north-east tracked east for 8 s, 28 m off)."""
    velocity = mean[[1, 4]]
    spread = float(np.linalg.eigvalsh(cov[np.ix_([1, 4], [1, 4])])[-1])
    return float(velocity @ velocity) >= HEADING_SIGMAS**2 * max(spread, 0.0)


def wait_for_heading(
    epoch: Sequence[int],
    observations: Sequence[Observation],
    uses: dict[int, MeasurementUse],
    odometer_t: float | None,
    t: float,
    reason: str = "heading not yet known (speed within 5 sigma of zero): dead reckoning waits for the fixes",
) -> float | None:
    """Report the epoch's gyro and odometer readings unused with ``reason`` (by default: until
    :func:`heading_known`); returns the odometer interval's new start (a distance reading still starts
    the next interval)."""
    for kind in (GyroObservation, OdometerObservation):
        readings = [i for i in epoch if isinstance(observations[i], kind)]
        for i in readings[:1]:
            uses[i] = MeasurementUse(i, observations[i].kind, False, reason)
        for i in readings[1:]:
            uses[i] = MeasurementUse(
                i,
                observations[i].kind,
                False,
                f"another {observations[i].kind} reading at the same time was used",
            )
    odos = [i for i in epoch if isinstance(observations[i], OdometerObservation)]
    # odos index the odometer readings the isinstance filter found (cast: free at run time)
    if odos and cast(OdometerObservation, observations[odos[0]]).distance is not None:
        return t
    return odometer_t
