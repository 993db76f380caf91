"""Published tracks: what a session makes known of its vehicle to cooperative neighbours, and how a
neighbour's position at a measurement time is read back from it.

The service calls :func:`publish` after every applied batch and stores the result under the vehicle's
id as one value; evaluation calls the same function, so in-process runs see exactly what a server
would serve. :func:`position_at` is the one rule every cooperative pipeline uses to turn a track into
a position and covariance at time t: interpolated inside the history, predicted forward (constant
velocity, covariance grown by white acceleration) past its end.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.pipelines.base import Fix, NeighbourTrack, TrackPoint

TRACK_HISTORY_POINTS = 20
"""How many of a vehicle's latest estimates its published track keeps (4 s at the paper's 0.2 s step)."""


def track_points(fixes: Sequence[Fix]) -> list[TrackPoint]:
    """The fixes that carry a position, velocity and 4x4 [x, y, vx, vy] covariance, as track points
    (a fix's ``shared`` estimate in its place when it has one). A "diverged" fix is never shared: its
    estimate is physically implausible (``pipelines.plausibility``)."""
    points = []
    for fix in fixes:
        if fix.status == "diverged":
            continue
        if fix.shared is not None:
            points.append(fix.shared)
            continue
        if fix.kinematic_cov is None or fix.x is None or fix.y is None or fix.vx is None or fix.vy is None:
            continue
        cov = tuple(tuple(float(v) for v in row) for row in fix.kinematic_cov)
        points.append(TrackPoint(fix.t, fix.x, fix.y, fix.vx, fix.vy, cov))
    return points


def publish(
    vehicle_id: str,
    previous: NeighbourTrack | None,
    fixes: Sequence[Fix],
    keep: int = TRACK_HISTORY_POINTS,
) -> NeighbourTrack | None:
    """The vehicle's track after a batch: the previous points older than this batch's first new one,
    then the new ones, the last ``keep`` of them. None when the batch brought no point."""
    new = track_points(fixes)
    if not new:
        return None
    old = [] if previous is None else [p for p in previous.points if p.t < new[0].t]
    return NeighbourTrack(vehicle_id, tuple((old + new)[-keep:]))


@dataclass(frozen=True)
class NeighbourPosition:
    """A neighbour's position (m) at a time and its 2x2 covariance (m^2)."""

    position: np.ndarray
    cov: np.ndarray
    source: str  # "history" (inside the published points) or "predicted" (past the last point)


class NeighbourUnavailable(Exception):
    """Why a neighbour's position cannot be used at a time (the message is the fix's reason)."""


def position_at(
    track: NeighbourTrack | None,
    t: float,
    max_age: float,
    accel_std: float,
    self_id: str | None = None,
    peer_id: str | None = None,
) -> NeighbourPosition:
    """The neighbour's position at ``t`` from its published ``track``.

    Inside the history: linear interpolation between the two points around ``t`` (covariance
    interpolated the same way; exact at a point). Past the last point by ``dt`` <= ``max_age``:
    constant-velocity prediction with covariance F P F^T + Q, Q the white-acceleration noise of
    1-sigma ``accel_std`` (m/s^2) held over the interval. Before the history, past ``max_age``, or
    the vehicle itself (``peer_id``, the id the measurement names, or the track's, equal to
    ``self_id``): :class:`NeighbourUnavailable` with the reason.
    """
    if self_id is not None and peer_id == self_id:
        raise NeighbourUnavailable("peer is this vehicle itself")
    if track is None:
        raise NeighbourUnavailable(
            "peer has no live session of a cooperative pipeline, or has published no estimate yet"
        )
    if self_id is not None and track.vehicle_id == self_id:
        raise NeighbourUnavailable("peer is this vehicle itself")
    points = track.points
    if not points:
        raise NeighbourUnavailable("peer has published no estimate yet")
    last = points[-1]
    if t >= last.t:
        dt = t - last.t
        if dt > max_age:
            raise NeighbourUnavailable(
                f"peer's latest estimate is {dt:.3g} s older than the measurement (max_neighbour_age {max_age:g} s)"
            )
        return _predict(last, dt, accel_std)
    first = points[0]
    if t < first.t:
        raise NeighbourUnavailable(
            f"measurement is {first.t - t:.3g} s older than the peer's published history"
        )
    times = [p.t for p in points]
    upper = int(np.searchsorted(times, t, side="right"))
    before, after = points[upper - 1], points[upper]
    span = after.t - before.t
    weight = 0.0 if span <= 0.0 else (t - before.t) / span
    pos = (1.0 - weight) * np.array([before.x, before.y]) + weight * np.array([after.x, after.y])
    cov = (1.0 - weight) * np.array(before.cov)[:2, :2] + weight * np.array(after.cov)[:2, :2]
    return NeighbourPosition(pos, 0.5 * (cov + cov.T), "history")


def _predict(point: TrackPoint, dt: float, accel_std: float) -> NeighbourPosition:
    mean = np.array([point.x + point.vx * dt, point.y + point.vy * dt])
    cov4 = np.array(point.cov, dtype=float)
    if dt == 0.0:
        cov = cov4[:2, :2]
    else:
        transition = np.array([[1.0, 0.0, dt, 0.0], [0.0, 1.0, 0.0, dt]])
        q = accel_std**2
        position_noise = q * dt**4 / 4.0
        cov = transition @ cov4 @ transition.T + np.eye(2) * position_noise
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))) or math.isnan(dt):
        raise NeighbourUnavailable("peer's published estimate is not finite")
    return NeighbourPosition(mean, 0.5 * (cov + cov.T), "predicted")
