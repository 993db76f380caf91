"""An urban drive through a city grid and the street canyons that mask its sky.

The route is a chain of :mod:`edgepos.sim.trajectory` segments plus :class:`Turn` (a 90-degree corner).
Every run of non-turn segments is one *street*: a straight line at the heading it is driven on, lined
on both sides by façades. Along a street, building blocks alternate with cross-street gaps; each block
side has its own height and each street its own façade-to-façade width, drawn once from the city's
seed (the city is the same in every Monte Carlo run; only the measurement errors change).

Street-canyon mask: a satellite at azimuth ``az`` seen from a street of azimuth ``psi`` (both clockwise
from north) has relative azimuth beta = az - psi; its ray leaves the street through the façade on its
side (right when sin beta > 0) at horizontal distance d / |sin beta|, with d the perpendicular distance
from the antenna to that façade, so it is blocked below the cut-off elevation
atan((H - antenna height) |sin beta| / d). Along the street (beta = 0) the sky is open down to the
horizon; across it the cut-off is steepest. In a cross-street gap or a corner the sky is open along both
streets: the cut-off is the lower of the two canyons' (the perpendicular one with the same façades).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edgepos.sim.trajectory import Accelerate, Cruise, Segment, SegmentMotion, Truth, build_trajectory

ANTENNA_HEIGHT_M = 1.5
#: Right-hand traffic: the lane centre is this far right of the street's centre line (m).
LANE_OFFSET_M = 1.9


@dataclass(frozen=True)
class Turn(Segment):
    """A corner: heading changes by ``angle`` (rad, positive = left) at the entry speed.

    Turn rate omega(t) = (angle / D) (1 - cos(2 pi t / D)): zero at both ends, peak 2 angle / D at
    mid-turn; heading change angle (t / D - sin(2 pi t / D) / (2 pi)).
    """

    duration: float
    angle: float

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (math.isfinite(self.angle) and 0.0 < abs(self.angle) <= math.pi):
            raise ValueError(f"Turn: angle must be in (0, pi] in magnitude, got {self.angle}")

    def motion(self, tau: np.ndarray, speed0: float) -> SegmentMotion:
        phase = 2.0 * math.pi * tau / self.duration
        zeros = np.zeros_like(tau)
        return SegmentMotion(
            np.full_like(tau, speed0),
            self.angle * (tau / self.duration - np.sin(phase) / (2.0 * math.pi)),
            self.angle / self.duration * (1.0 - np.cos(phase)),
            zeros,
        )


@dataclass(frozen=True)
class CityParameters:
    """How the façades along every street are drawn (metres)."""

    seed: int = 32
    width_range: tuple[float, float] = (24.0, 45.0)
    """Façade-to-façade street width, per street (arterial roads with sidewalks)."""
    height_range: tuple[float, float] = (10.0, 45.0)
    """Building height, per block side."""
    block_range: tuple[float, float] = (80.0, 200.0)
    """Length of a block's frontage."""
    gap_m: float = 20.0
    """Width of a cross street between blocks."""


@dataclass(frozen=True, eq=False)
class StreetView:
    """Per sample of the truth: the canyon the vehicle is in.

    ``axis`` is the street's azimuth (rad, clockwise from north); ``left`` / ``right`` the perpendicular
    distances (m) to the façades and ``left_height`` / ``right_height`` their heights (m, 0 = no
    buildings); ``open_cross`` marks cross-street gaps and corners; ``place`` numbers the places
    (street block or gap), so effects that persist while the vehicle stays in one place can be keyed
    on it.
    """

    axis: np.ndarray
    left: np.ndarray
    right: np.ndarray
    left_height: np.ndarray
    right_height: np.ndarray
    open_cross: np.ndarray
    place: np.ndarray

    def cutoff(self, azimuth: np.ndarray) -> np.ndarray:
        """Cut-off elevation (rad) for satellites at ``azimuth`` (K, n) (clockwise from north)."""
        along = _canyon(azimuth - self.axis[:, None], self)
        across = _canyon(azimuth - self.axis[:, None] - 0.5 * math.pi, self)
        return np.where(self.open_cross[:, None], np.minimum(along, across), along)

    def facade_distance_opposite(self, azimuth: np.ndarray) -> np.ndarray:
        """Perpendicular distance (m) to the façade opposite a satellite's side (its reflector)."""
        right_side = np.sin(azimuth - self.axis[:, None]) > 0.0
        return np.where(right_side, self.left[:, None], self.right[:, None])


def _canyon(relative: np.ndarray, view: StreetView) -> np.ndarray:
    sine = np.sin(relative)
    right_side = sine > 0.0
    height = np.where(right_side, view.right_height[:, None], view.left_height[:, None]) - ANTENNA_HEIGHT_M
    distance = np.where(right_side, view.right[:, None], view.left[:, None])
    result: np.ndarray = np.arctan2(np.maximum(height, 0.0) * np.abs(sine), distance)
    return result


def nanjing_route() -> list[Segment]:
    """About 6.5 minutes through a downtown grid: six streets joined by five corners, a traffic-light stop,
    cruising at 10-14 m/s and slowing to 5 m/s for each corner."""
    corner_speed = 5.0
    segments: list[Segment] = [Cruise(2.0)]

    def street(cruise_speed: float, cruise_s: float, stop: float | None = None) -> None:
        rise = (cruise_speed - corner_speed) / 1.5
        segments.append(Accelerate(rise, 1.5))
        if stop is None:
            segments.append(Cruise(cruise_s))
        else:
            segments.append(Cruise(stop))
            segments.append(Accelerate(cruise_speed / 2.0, -2.0))
            segments.append(Cruise(20.0))  # standing at the light: speed 0
            segments.append(Accelerate(cruise_speed / 1.5, 1.5))
            segments.append(Cruise(cruise_s - stop))
        segments.append(Accelerate(rise, -1.5))

    street(12.0, 45.0)
    segments.append(Turn(4.0, 0.5 * math.pi))  # left: north
    street(10.0, 30.0, stop=15.0)
    segments.append(Turn(4.0, -0.5 * math.pi))  # right: east
    street(14.0, 60.0)
    segments.append(Turn(4.0, -0.5 * math.pi))  # right: south
    street(11.0, 40.0)
    segments.append(Turn(4.0, -0.5 * math.pi))  # right: west
    street(13.0, 70.0)
    segments.append(Turn(4.0, 0.5 * math.pi))  # left: south
    street(10.0, 35.0)
    return segments


def short_route() -> list[Segment]:
    """About 70 s: one street, a corner, a second street (for tests)."""
    return [
        Cruise(2.0),
        Accelerate(4.0, 1.5),
        Cruise(25.0),
        Accelerate(4.0, -1.5),
        Turn(4.0, 0.5 * math.pi),
        Accelerate(4.0, 1.5),
        Cruise(25.0),
    ]


def drive(segments: list[Segment], period: float, heading0: float = 0.0, speed0: float = 5.0) -> Truth:
    """The route's truth from the origin of the site frame (x east, y north), sampled every ``period`` s."""
    return build_trajectory(segments, heading0=heading0, speed0=speed0, period=period)


def street_view(truth: Truth, segments: list[Segment], city: CityParameters | None) -> StreetView:
    """The canyon at every truth sample; ``city`` None gives open sky (no buildings anywhere)."""
    count = truth.t.size
    owner = np.searchsorted(truth.segment_times[1:-1], truth.t + 1e-9, side="right")
    turning = np.array([isinstance(segments[i], Turn) for i in owner])
    # Streets: maximal runs of non-turn segments; a turn belongs to the street it leaves.
    street = np.zeros(count, dtype=int)
    current = 0
    for k in range(1, count):
        if not turning[k] and turning[k - 1]:
            current += 1
        street[k] = current
    streets = current + 1
    heading_north = 0.5 * math.pi - truth.heading  # clockwise from north
    axis = np.empty(count)
    along = np.empty(count)
    for s in range(streets):
        rows = np.flatnonzero((street == s) & ~turning)
        first = rows[0] if rows.size else np.flatnonzero(street == s)[0]
        axis_s = float(heading_north[first])
        axis[street == s] = axis_s
        direction = np.array([math.sin(axis_s), math.cos(axis_s)])
        offsets = np.stack([truth.x - truth.x[first], truth.y - truth.y[first]], axis=-1)
        along[street == s] = offsets[street == s] @ direction

    zeros = np.zeros(count)
    if city is None:
        return StreetView(axis, zeros + 1.0, zeros + 1.0, zeros, zeros, np.ones(count, bool), street)

    rng = np.random.default_rng(city.seed)
    width = rng.uniform(*city.width_range, streets)
    blocks = 64
    block_length = rng.uniform(*city.block_range, (streets, blocks))
    heights = rng.uniform(*city.height_range, (streets, blocks, 2))  # [.., 0] left, [.., 1] right
    # Block b of a street spans [start_b, start_b + length_b); gaps of gap_m separate blocks and the
    # street starts with half a gap (leaving the corner).
    starts = 0.5 * city.gap_m + np.concatenate(
        [np.zeros((streets, 1)), np.cumsum(block_length + city.gap_m, axis=1)[:, :-1]], axis=1
    )
    block = np.empty(count, dtype=int)
    in_gap = np.empty(count, dtype=bool)
    for k in range(count):
        s = street[k]
        b = int(np.searchsorted(starts[s], along[k], side="right")) - 1
        in_gap[k] = b < 0 or along[k] >= starts[s, b] + block_length[s, b]
        block[k] = max(b, 0)
    open_cross = in_gap | turning
    half = 0.5 * width[street]
    left = half + LANE_OFFSET_M
    right = np.maximum(half - LANE_OFFSET_M, 2.0)
    left_height = heights[street, block, 0]
    right_height = heights[street, block, 1]
    _, place = np.unique(street * (2 * blocks) + 2 * block + open_cross, return_inverse=True)
    return StreetView(axis, left, right, left_height, right_height, open_cross, place)
