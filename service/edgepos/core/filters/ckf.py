"""Cubature Kalman filter (Arasaratnam & Haykin 2009): the third-degree spherical-radial rule.

2m points sqrt(m) [I, -I] with equal weights 1/(2m) (RSU + IMU paper, eqs. 15-28, in their
standard form: the stray "+P" terms of eqs. 19, 23, 24 dropped, eq. 24 on the re-drawn points).
"""

from __future__ import annotations

import functools

import numpy as np

from edgepos.core.filters.sigma_points import SigmaPointFilter


class CubatureKalmanFilter(SigmaPointFilter):
    """All weights positive, so every covariance it forms is positive semidefinite."""

    name = "ckf"

    def unit_points(self, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _cubature_points(dim)


@functools.lru_cache(maxsize=16)
def _cubature_points(dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    offsets = np.sqrt(dim) * np.vstack([np.eye(dim), -np.eye(dim)])
    weights = np.full(2 * dim, 1.0 / (2 * dim))
    for array in (offsets, weights):
        array.setflags(write=False)
    return offsets, weights, weights
