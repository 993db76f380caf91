"""Plane geometry of operator-defined zones and of the location adapter's summaries of a fix.

Everything is in the site frame (x east, y north, metres). Pure ``math``: no web or numpy imports.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

CIRCLE_95_SCALE = math.sqrt(-2.0 * math.log(0.05))
"""sqrt of the chi-square 95% quantile with 2 degrees of freedom (2.4477): a circle of this many standard
deviations of the major axis holds a 2-D Gaussian position with at least 95% probability."""


@dataclass(frozen=True)
class Circle:
    """A disc: centre (x, y) and radius (m)."""

    x: float
    y: float
    radius: float

    def contains(self, x: float, y: float) -> bool:
        return math.hypot(x - self.x, y - self.y) <= self.radius


@dataclass(frozen=True)
class Polygon:
    """A simple polygon given by its vertices (m), in either winding order; the last edge closes it."""

    vertices: tuple[tuple[float, float], ...]

    def contains(self, x: float, y: float) -> bool:
        """Even-odd ray casting: a point on an edge may fall either way (zones are metres wide)."""
        inside = False
        points = self.vertices
        previous = points[-1]
        for current in points:
            (x1, y1), (x2, y2) = previous, current
            if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
                inside = not inside
            previous = current
        return inside

    def area(self) -> float:
        """Unsigned area (m^2) by the shoelace formula."""
        points = self.vertices
        twice = sum(
            points[i - 1][0] * points[i][1] - points[i][0] * points[i - 1][1] for i in range(len(points))
        )
        return abs(twice) / 2.0


Shape = Circle | Polygon


def polygon_self_intersects(vertices: Sequence[tuple[float, float]]) -> bool:
    """Whether two non-adjacent edges of the closed polygon cross (such a zone has no clear inside)."""

    def orientation(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> float:
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    count = len(vertices)
    edges = [(vertices[i], vertices[(i + 1) % count]) for i in range(count)]
    for i in range(count):
        for j in range(i + 1, count):
            if j == i + 1 or (i == 0 and j == count - 1):
                continue  # adjacent edges share a vertex
            (p1, p2), (q1, q2) = edges[i], edges[j]
            d1, d2 = orientation(q1, q2, p1), orientation(q1, q2, p2)
            d3, d4 = orientation(p1, p2, q1), orientation(p1, p2, q2)
            if d1 * d2 < 0 and d3 * d4 < 0:
                return True
    return False


def circle_accuracy(covariance: Sequence[Sequence[float]]) -> float:
    """Radius (m) of a circle about the estimate holding the true position with >= 95% probability,
    from the 2x2 position covariance (m^2): CIRCLE_95_SCALE standard deviations of the major axis."""
    xx, xy, yy = covariance[0][0], covariance[0][1], covariance[1][1]
    major = 0.5 * (xx + yy) + math.sqrt(max(0.0, 0.25 * (xx - yy) ** 2 + xy * xy))
    return CIRCLE_95_SCALE * math.sqrt(max(0.0, major))


def bearing_deg(vx: float, vy: float) -> float:
    """Direction of travel in degrees clockwise from north in [0, 360), from east/north velocity (m/s)."""
    return math.degrees(math.atan2(vx, vy)) % 360.0
