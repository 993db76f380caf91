"""The vehicle pseudo-measurements of gnss_tight without RISS: what the rows measure."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.motion import riss as layout
from edgepos.pipelines.gnss_constraints import NHC_MIN_SPEED_MPS, non_holonomic, zero_velocity


def _state(ve: float, vn: float, vu: float) -> np.ndarray:
    state = np.zeros(layout.DIM)
    state[[layout.VE, layout.VN, layout.VU]] = ve, vn, vu
    return state


def test_non_holonomic_rows_measure_lateral_and_vertical_velocity() -> None:
    heading = _state(3.0, 4.0, 0.0)  # azimuth atan2(3, 4)
    constraint = non_holonomic(heading, 1.0, 1.0, 0.3)
    assert constraint is not None and constraint.name == "non-holonomic"
    assert constraint.predict(heading) == pytest.approx([0.0, 0.0], abs=1e-12)
    # 1 m/s to the right of the heading (east-south of north-east travel), 0.2 m/s up
    right = np.array([4.0, -3.0]) / 5.0
    moved = _state(3.0 + right[0], 4.0 + right[1], 0.2)
    assert constraint.predict(moved) == pytest.approx([1.0, 0.2])
    # along the heading nothing is measured
    assert constraint.predict(_state(6.0, 8.0, 0.0)) == pytest.approx([0.0, 0.0], abs=1e-12)
    assert constraint.variances == pytest.approx([1.0, 0.09])
    # the lateral std grows with the interval, a batch of particles is predicted at once
    assert non_holonomic(heading, 2.0, 1.0, 0.3).variances[0] == pytest.approx(4.0)  # type: ignore[union-attr]
    assert constraint.predict(np.stack([heading, moved])).shape == (2, 2)


def test_no_non_holonomic_frame_at_rest() -> None:
    assert non_holonomic(_state(0.5 * NHC_MIN_SPEED_MPS, 0.0, 0.0), 1.0, 1.0, 0.3) is None


def test_zero_velocity_rows() -> None:
    constraint = zero_velocity(0.05)
    assert constraint.predict(_state(0.1, -0.2, 0.3)) == pytest.approx([0.1, -0.2, 0.3])
    assert constraint.variances == pytest.approx([0.0025] * 3)
    assert math.isclose(float(constraint.rows.sum()), 3.0)
