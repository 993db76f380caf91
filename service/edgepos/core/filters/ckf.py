"""Cubature Kalman filter (Arasaratnam & Haykin 2009): the third-degree spherical-radial rule.

2m points mean +- sqrt(m) L e_i with equal weights 1/(2m) (RSU + IMU paper, eqs. 15-28, in their
standard form: the stray "+P" terms of eqs. 19, 23, 24 dropped, eq. 24 on the re-drawn points).
All weights are positive, so every covariance it forms is positive semidefinite.
"""

from __future__ import annotations

import math

from edgepos.core.filters.sigma_points import SigmaPointFilter


class CubatureKalmanFilter(SigmaPointFilter):
    """The spherical-radial cubature rule."""

    name = "ckf"

    def point_weights(self, dim: int) -> tuple[float, float, float, float]:
        return math.sqrt(dim), 1.0 / (2 * dim), 0.0, 0.0

    def __hash__(self) -> int:
        return hash(self.name)

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self)
