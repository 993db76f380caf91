"""The 8-dimensional vehicle state of the RSU + IMU paper and its index names.

State vector: ``[xp, xv, xa, yp, yv, ya, phi, omega]`` in a site-local east-north frame:
positions in metres, velocities in m/s, accelerations in m/s^2, heading ``phi`` in radians
counter-clockwise from the +x (east) axis, turn rate ``omega`` in rad/s (counter-clockwise positive).
Motion models use subsets of these components; a sub-state is always ordered as in the full state.
"""

from __future__ import annotations

import numpy as np

XP, XV, XA, YP, YV, YA, PHI, OMEGA = range(8)
FULL_DIM = 8
NAMES = ("xp", "xv", "xa", "yp", "yv", "ya", "phi", "omega")
ANGLE_COMPONENTS = frozenset({PHI})

POSITION_VELOCITY = (XP, XV, YP, YV)
KINEMATIC = (XP, XV, XA, YP, YV, YA)
ALL = tuple(range(FULL_DIM))


def angle_mask(components: tuple[int, ...]) -> np.ndarray:
    """Boolean mask of the sub-state entries that are angles (wrapped to (-pi, pi])."""
    return np.array([c in ANGLE_COMPONENTS for c in components], dtype=bool)


def embed(points: np.ndarray, components: tuple[int, ...]) -> np.ndarray:
    """Place sub-state rows ``points`` (n, m) into full-state rows (n, 8), zeros elsewhere.

    Missing components are zero: a CV model has no acceleration, so it predicts a zero yaw rate.
    """
    full = np.zeros((points.shape[0], FULL_DIM))
    full[:, components] = points
    return full


#: Angle flags of the full state (heading only).
FULL_ANGLE_MASK = angle_mask(ALL)
