"""What the kinematic pipelines share: the fix of a [xp, xv, xa, yp, yv, ya] Gaussian."""

from __future__ import annotations

import math

import numpy as np

from edgepos.core import layout
from edgepos.pipelines.base import Fix, MeasurementUse, TrackPoint

KINEMATIC = layout.KINEMATIC
_TRACK_ORDER = [0, 3, 1, 4]  # [x, y, vx, vy] of the published track


def kinematic_fix(t: float, status: str, mean: np.ndarray, cov: np.ndarray, uses: list[MeasurementUse]) -> Fix:
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
        t, float(mean[0]), float(mean[3]), float(mean[1]), float(mean[4]),
        tuple(tuple(float(v) for v in row) for row in block),
    )
