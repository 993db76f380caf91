"""The truth trajectory of the RSU + IMU paper's scenario and the segment building blocks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.sim.scenarios import LANE_WIDTH, PAPER_SEGMENTS, ROAD_EDGES, rsu_imu_paper_scenario
from edgepos.sim.trajectory import Accelerate, Cruise, LaneChange, Truth, UTurn, build_trajectory


@pytest.fixture(scope="module")
def truth() -> Truth:
    return rsu_imu_paper_scenario().truth


def sample_index(truth: Truth, t: float) -> int:
    index = round(t / (truth.t[1] - truth.t[0]))
    assert truth.t[index] == pytest.approx(t, abs=1e-9)
    return index


def segment_spans(truth: Truth, kind: type) -> list[tuple[int, int]]:
    """(start, end) sample indices of the paper's segments of type ``kind``."""
    times = truth.segment_times
    return [
        (sample_index(truth, times[i]), sample_index(truth, times[i + 1]))
        for i, segment in enumerate(PAPER_SEGMENTS)
        if isinstance(segment, kind)
    ]


def test_sampling_grid_and_initial_state(truth: Truth) -> None:
    assert truth.t.size == 801
    np.testing.assert_allclose(truth.t, np.arange(801) * 0.05, rtol=0, atol=1e-12)
    np.testing.assert_allclose(truth.segment_times[-1], 40.0)
    scenario = rsu_imu_paper_scenario()
    assert scenario.initial_state == pytest.approx((0.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), abs=1e-12)


def test_speeds_at_segment_ends_match_table_1(truth: Truth) -> None:
    ends = [sample_index(truth, t) for t in truth.segment_times[1:]]
    expected = [10, 20, 20, 25, 5, 5, 15, 15, 25, 25, 16, 16]
    np.testing.assert_allclose(truth.speed[ends], expected, atol=1e-9)
    np.testing.assert_allclose(np.hypot(truth.vx, truth.vy), truth.speed, atol=1e-9)


def test_lane_changes_shift_one_lane_and_restore_heading(truth: Truth) -> None:
    spans = segment_spans(truth, LaneChange)
    np.testing.assert_allclose(
        [(truth.y[a], truth.y[b]) for a, b in spans],
        [(0.0, LANE_WIDTH), (3 * LANE_WIDTH, 2 * LANE_WIDTH), (2 * LANE_WIDTH, 3 * LANE_WIDTH)],
        rtol=0,
        atol=1e-6,
    )
    for a, b in spans:
        turned = math.remainder(truth.heading[b] - truth.heading[a], 2 * math.pi)
        assert turned == pytest.approx(0.0, abs=1e-12)
        assert np.all(np.diff(truth.y[a : b + 1]) * np.sign(truth.y[b] - truth.y[a]) >= 0)


def test_u_turn_reverses_heading_and_shifts_two_lanes(truth: Truth) -> None:
    [(a, b)] = segment_spans(truth, UTurn)
    heading = np.unwrap(truth.heading)
    assert heading[b] - heading[a] == pytest.approx(math.pi, abs=1e-9)
    assert truth.y[b] - truth.y[a] == pytest.approx(2 * LANE_WIDTH, abs=1e-6)
    assert truth.x[b] == pytest.approx(truth.x[a], abs=1e-6)
    assert truth.speed[a : b + 1] == pytest.approx(5.0)


def test_yaw_rate_is_the_heading_derivative(truth: Truth) -> None:
    # Central differences at T = 0.05 s are off by T^2/6 * omega'': up to ~2e-3 rad/s in the U-turn.
    period = truth.t[1] - truth.t[0]
    heading = np.unwrap(truth.heading)
    derivative = (heading[2:] - heading[:-2]) / (2 * period)
    np.testing.assert_allclose(derivative, truth.yaw_rate[1:-1], rtol=0, atol=5e-3)


def test_acceleration_is_the_velocity_derivative(truth: Truth) -> None:
    # Same O(T^2) central-difference error (~1.5e-2 m/s^2 in the U-turn); samples next to a segment
    # boundary are skipped because longitudinal acceleration steps there.
    period = truth.t[1] - truth.t[0]
    derivative_x = (truth.vx[2:] - truth.vx[:-2]) / (2 * period)
    derivative_y = (truth.vy[2:] - truth.vy[:-2]) / (2 * period)
    interior = truth.t[1:-1]
    smooth = np.all(np.abs(interior[:, None] - truth.segment_times[None, :]) > 1.01 * period, axis=1)
    assert smooth.sum() > 700
    np.testing.assert_allclose(derivative_x[smooth], truth.ax[1:-1][smooth], rtol=0, atol=3e-2)
    np.testing.assert_allclose(derivative_y[smooth], truth.ay[1:-1][smooth], rtol=0, atol=3e-2)


def test_position_is_continuous_and_integrates_velocity(truth: Truth) -> None:
    period = truth.t[1] - truth.t[0]
    steps = np.hypot(np.diff(truth.x), np.diff(truth.y))
    assert np.all(steps <= np.maximum(truth.speed[1:], truth.speed[:-1]) * period + 1e-9)
    trapezoid_x = 0.5 * period * (truth.vx[1:] + truth.vx[:-1])
    trapezoid_y = 0.5 * period * (truth.vy[1:] + truth.vy[:-1])
    np.testing.assert_allclose(np.diff(truth.x), trapezoid_x, rtol=0, atol=5e-3)
    np.testing.assert_allclose(np.diff(truth.y), trapezoid_y, rtol=0, atol=5e-3)


def test_vehicle_stays_on_the_road(truth: Truth) -> None:
    assert ROAD_EDGES[0] < truth.y.min() and truth.y.max() < ROAD_EDGES[1]
    assert np.all((truth.heading >= -math.pi) & (truth.heading < math.pi))


def test_segments_refuse_impossible_motion() -> None:
    with pytest.raises(ValueError, match="negative speed"):
        build_trajectory([Accelerate(3.0, -5.0)], speed0=10.0, period=0.05)
    with pytest.raises(ValueError, match="not reachable"):
        build_trajectory([LaneChange(1.0, 20.0)], speed0=10.0, period=0.05)
    with pytest.raises(ValueError, match="not reachable"):
        build_trajectory([UTurn(4.2, 20.0)], speed0=5.0, period=0.05)
    with pytest.raises(ValueError):
        Cruise(0.0)


def test_right_u_turn_mirrors_left() -> None:
    left = build_trajectory([UTurn(4.0, 6.0)], heading0=0.5, speed0=4.0, period=0.1)
    right = build_trajectory([UTurn(4.0, -6.0)], heading0=0.5, speed0=4.0, period=0.1)
    np.testing.assert_allclose(right.yaw_rate, -left.yaw_rate, atol=1e-12)

    def shift(truth: Truth) -> float:
        """Displacement to the left of the entry heading."""
        return -(truth.x[-1] - truth.x[0]) * math.sin(0.5) + (truth.y[-1] - truth.y[0]) * math.cos(0.5)

    assert shift(left) == pytest.approx(6.0, abs=1e-6)
    assert shift(right) == pytest.approx(-6.0, abs=1e-6)
