"""Zone geometry and the location adapter's summaries of a fix (edgepos.core.zones)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.zones import (
    CIRCLE_95_SCALE,
    Circle,
    Polygon,
    bearing_deg,
    circle_accuracy,
    polygon_self_intersects,
)

L_SHAPE = Polygon(((0.0, 0.0), (20.0, 0.0), (20.0, 10.0), (10.0, 10.0), (10.0, 20.0), (0.0, 20.0)))


@pytest.mark.parametrize(
    ("point", "inside"),
    [
        ((5.0, 5.0), True),
        ((15.0, 5.0), True),
        ((5.0, 15.0), True),
        ((15.0, 15.0), False),
        ((-1.0, 5.0), False),
        ((25.0, 5.0), False),
    ],
)
def test_a_concave_polygon_holds_its_inside_only(point, inside):
    assert L_SHAPE.contains(*point) is inside
    reversed_shape = Polygon(tuple(reversed(L_SHAPE.vertices)))
    assert reversed_shape.contains(*point) is inside  # either winding order


def test_polygon_area_and_circle():
    assert L_SHAPE.area() == 300.0
    circle = Circle(3.0, 4.0, 5.0)
    assert circle.contains(0.0, 0.0) and circle.contains(8.0, 4.0) and not circle.contains(8.1, 4.0)


def test_crossing_edges_are_found():
    assert polygon_self_intersects([(0.0, 0.0), (10.0, 10.0), (10.0, 0.0), (0.0, 10.0)])
    assert not polygon_self_intersects(list(L_SHAPE.vertices))


def test_the_95_percent_circle_holds_95_percent_of_gaussian_positions():
    assert CIRCLE_95_SCALE == pytest.approx(2.4477468, abs=1e-6)
    covariance = [[4.0, 0.0], [0.0, 4.0]]  # isotropic: the bound is exact
    radius = circle_accuracy(covariance)
    samples = np.random.default_rng(3).multivariate_normal([0.0, 0.0], covariance, size=200_000)
    share = float(np.mean(np.hypot(samples[:, 0], samples[:, 1]) <= radius))
    assert share == pytest.approx(0.95, abs=0.003)
    elongated = [[9.0, 2.0], [2.0, 1.0]]  # the major axis bounds it: at least 95%
    samples = np.random.default_rng(4).multivariate_normal([0.0, 0.0], elongated, size=200_000)
    assert float(np.mean(np.hypot(samples[:, 0], samples[:, 1]) <= circle_accuracy(elongated))) >= 0.95
    assert circle_accuracy(elongated) == pytest.approx(
        CIRCLE_95_SCALE * math.sqrt(5.0 + math.sqrt(20.0)), rel=1e-12
    )


@pytest.mark.parametrize(
    ("vx", "vy", "bearing"),
    [(0.0, 1.0, 0.0), (1.0, 0.0, 90.0), (0.0, -1.0, 180.0), (-1.0, 0.0, 270.0), (-1.0, 1.0, 315.0)],
)
def test_bearing_is_clockwise_from_north(vx, vy, bearing):
    assert bearing_deg(vx, vy) == pytest.approx(bearing)
