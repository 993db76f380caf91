"""Noise-free vehicle trajectories built from reusable motion segments.

A trajectory is a chain of segments (cruise, accelerate, lane change, U-turn). Each segment gives
its speed, heading change, yaw rate and longitudinal acceleration in closed form, as functions of
the time since it began and the speed it was entered with, so a scenario is just a list of
segments. :func:`build_trajectory` evaluates the chain on a fine grid, integrates the velocity to
positions (cumulative trapezoid) and samples everything at the sensor period. The result,
:class:`Truth`, is what simulated sensors measure and what estimates are scored against.

Conventions: site frame with x east and y north (m); heading counter-clockwise from +x (rad);
a positive lateral offset is to the vehicle's left.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.optimize import brentq
from scipy.special import beta, betainc, j0

from edgepos.core.numerics import wrap_angle

#: Gauss-Legendre rule on theta in [0, pi] for the U-turn's lateral-displacement integral.
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(256)
_THETA = 0.5 * math.pi * (_GL_NODES + 1.0)
_THETA_WEIGHTS = 0.5 * math.pi * _GL_WEIGHTS

#: Sharpest U-turn profile considered: at p = 100 the shift is already below 5 % of speed * duration
#: (nearly turning on the spot), and the quadrature above still resolves the profile.
MAX_U_TURN_SHARPNESS = 100.0

#: A fine-grid time within this of a segment boundary belongs to the later segment.
_BOUNDARY_TOLERANCE = 1e-9


class SegmentMotion(NamedTuple):
    """A segment's kinematics at the times ``tau`` since it began (arrays shaped like ``tau``)."""

    speed: np.ndarray
    """Speed (m/s)."""
    heading_change: np.ndarray
    """Heading relative to the entry heading (rad)."""
    yaw_rate: np.ndarray
    """Turn rate (rad/s, counter-clockwise positive)."""
    acceleration: np.ndarray
    """Longitudinal acceleration along the heading (m/s^2)."""


class Segment(ABC):
    """One piece of a trajectory lasting ``duration`` seconds, relative to how it is entered."""

    duration: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.duration) and self.duration > 0.0):
            raise ValueError(f"{type(self).__name__}: duration must be positive, got {self.duration}")

    @abstractmethod
    def motion(self, tau: np.ndarray, speed0: float) -> SegmentMotion:
        """Kinematics at ``tau`` (0 <= tau <= duration) for a vehicle entering at ``speed0``."""


@dataclass(frozen=True)
class Cruise(Segment):
    """Straight ahead at the entry speed."""

    duration: float

    def motion(self, tau: np.ndarray, speed0: float) -> SegmentMotion:
        zeros = np.zeros_like(tau)
        return SegmentMotion(np.full_like(tau, speed0), zeros, zeros, zeros)


@dataclass(frozen=True)
class Accelerate(Segment):
    """Straight ahead with constant longitudinal ``acceleration`` (m/s^2; negative = braking)."""

    duration: float
    acceleration: float

    def motion(self, tau: np.ndarray, speed0: float) -> SegmentMotion:
        final = speed0 + self.acceleration * self.duration
        if final < 0.0:
            raise ValueError(
                f"Accelerate({self.duration} s, {self.acceleration} m/s^2) from {speed0} m/s "
                f"would end at a negative speed ({final} m/s)"
            )
        zeros = np.zeros_like(tau)
        speed = speed0 + self.acceleration * tau
        return SegmentMotion(speed, zeros, zeros, np.full_like(tau, self.acceleration))


@dataclass(frozen=True)
class LaneChange(Segment):
    """A sideways shift by ``offset`` metres (positive = left) at the entry speed.

    Heading follows psi(t) = psi_max * sin^2(pi t / D): the turn rate starts and ends at zero and
    the heading returns to its start value. At constant speed v the lateral shift is
    v * D * sin(psi_max / 2) * J0(psi_max / 2) (average of sin(psi_max sin^2) over a period),
    increasing in psi_max up to pi / 2, so psi_max is found by root bracketing on [0, pi / 2].
    """

    duration: float
    offset: float

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (math.isfinite(self.offset) and self.offset != 0.0):
            raise ValueError(f"LaneChange: offset must be finite and non-zero, got {self.offset}")

    def lateral_shift(self, peak_heading: float, speed: float) -> float:
        """Sideways displacement (m) of the profile with ``peak_heading`` at constant ``speed``."""
        half = 0.5 * peak_heading
        return speed * self.duration * math.sin(half) * float(j0(half))

    def peak_heading(self, speed: float) -> float:
        """psi_max (rad, signed like ``offset``) that shifts the vehicle by ``offset`` at ``speed``."""
        target = abs(self.offset)
        reachable = self.lateral_shift(0.5 * math.pi, speed)
        if not target <= reachable:
            raise ValueError(
                f"LaneChange: {target} m in {self.duration} s at {speed} m/s is not reachable "
                f"(at most {reachable:.3f} m)"
            )
        magnitude = brentq(
            lambda psi: self.lateral_shift(psi, speed) - target, 0.0, 0.5 * math.pi, xtol=1e-15
        )
        return math.copysign(magnitude, self.offset)

    def motion(self, tau: np.ndarray, speed0: float) -> SegmentMotion:
        peak = self.peak_heading(speed0)
        rate = math.pi / self.duration
        zeros = np.zeros_like(tau)
        return SegmentMotion(
            np.full_like(tau, speed0),
            peak * np.sin(rate * tau) ** 2,
            peak * rate * np.sin(2.0 * rate * tau),
            zeros,
        )


def _turn_fraction(theta: np.ndarray, sharpness: float) -> np.ndarray:
    """Share of a sin^(2p) turn-rate profile completed at phase theta in [0, pi] (0 -> 1).

    int_0^theta sin^(2p) = B(p + 1/2, 1/2) * I_{sin^2 theta}(p + 1/2, 1/2) / 2 on [0, pi / 2], with
    I the regularised incomplete beta function; the profile's symmetry gives the second half.
    """
    half = 0.5 * betainc(sharpness + 0.5, 0.5, np.sin(theta) ** 2)
    result: np.ndarray = np.where(theta <= 0.5 * math.pi, half, 1.0 - half)
    return result


@dataclass(frozen=True)
class UTurn(Segment):
    """Reverse direction (heading +pi for ``offset`` > 0, a left U-turn; -pi otherwise) at the entry speed.

    The turn rate is bell-shaped, omega(t) proportional to sin^(2p)(pi t / D) and normalised to turn
    by pi. A flat profile (small p) sweeps a wide arc; a sharp one (large p) turns almost on the
    spot. The sharpness p >= 1 is solved so that the sideways shift equals ``|offset|``; the shift
    falls as p grows, so offsets outside [shift(MAX_U_TURN_SHARPNESS), shift(1)] raise ValueError.
    By symmetry the vehicle leaves at the longitudinal position it entered at.
    """

    duration: float
    offset: float

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (math.isfinite(self.offset) and self.offset != 0.0):
            raise ValueError(f"UTurn: offset must be finite and non-zero, got {self.offset}")

    def lateral_shift(self, sharpness: float, speed: float) -> float:
        """Sideways displacement (m) of the profile with ``sharpness`` p at constant ``speed``."""
        heading = math.pi * _turn_fraction(_THETA, sharpness)
        return speed * self.duration / math.pi * float(_THETA_WEIGHTS @ np.sin(heading))

    def sharpness(self, speed: float) -> float:
        """The exponent p of the sin^(2p) turn-rate profile that shifts the vehicle by ``|offset|``."""
        target = abs(self.offset)
        widest = self.lateral_shift(1.0, speed)
        narrowest = self.lateral_shift(MAX_U_TURN_SHARPNESS, speed)
        if not narrowest <= target <= widest:
            raise ValueError(
                f"UTurn: a {target} m shift in {self.duration} s at {speed} m/s is not reachable "
                f"(between {narrowest:.3f} and {widest:.3f} m)"
            )
        return float(
            brentq(lambda p: self.lateral_shift(p, speed) - target, 1.0, MAX_U_TURN_SHARPNESS, xtol=1e-13)
        )

    def peak_yaw_rate(self, sharpness: float) -> float:
        """Turn rate (rad/s, signed) at mid-turn for the profile with ``sharpness`` p."""
        return math.copysign(math.pi**2 / (self.duration * beta(sharpness + 0.5, 0.5)), self.offset)

    def motion(self, tau: np.ndarray, speed0: float) -> SegmentMotion:
        sharpness = self.sharpness(speed0)
        theta = math.pi * tau / self.duration
        sign = math.copysign(1.0, self.offset)
        zeros = np.zeros_like(tau)
        return SegmentMotion(
            np.full_like(tau, speed0),
            sign * math.pi * _turn_fraction(theta, sharpness),
            self.peak_yaw_rate(sharpness) * (np.sin(theta) ** 2) ** sharpness,
            zeros,
        )


@dataclass(frozen=True, eq=False)
class Truth:
    """The true motion sampled at t_k = k * period, k = 0..K (arrays of length K + 1, SI units).

    ``heading`` is wrapped to [-pi, pi); ``ax``, ``ay`` are the total acceleration (longitudinal plus
    centripetal speed * yaw_rate), the derivative of (``vx``, ``vy``). ``segment_times`` holds the
    start time of each segment and the end of the last one.
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    ax: np.ndarray
    ay: np.ndarray
    heading: np.ndarray
    yaw_rate: np.ndarray
    speed: np.ndarray
    segment_times: np.ndarray


def build_trajectory(
    segments: Sequence[Segment],
    *,
    start: tuple[float, float] = (0.0, 0.0),
    heading0: float = 0.0,
    speed0: float,
    period: float,
    fine_step: float = 1e-3,
) -> Truth:
    """Chain ``segments`` from ``start``, ``heading0`` (rad) and ``speed0`` (m/s); sample every ``period`` s.

    Speed, heading, yaw rate and acceleration are evaluated in closed form on a grid of about
    ``fine_step`` seconds that contains every sample time; positions are the cumulative trapezoid
    of the velocity on that grid. Samples run up to the last whole period of the total duration.
    """
    if not segments:
        raise ValueError("build_trajectory: no segments")
    if not period > 0.0:
        raise ValueError(f"build_trajectory: period must be positive, got {period}")
    if not speed0 >= 0.0:
        raise ValueError(f"build_trajectory: speed0 must be non-negative, got {speed0}")
    segment_times = np.concatenate([[0.0], np.cumsum([segment.duration for segment in segments])])
    samples = math.floor(segment_times[-1] / period + _BOUNDARY_TOLERANCE)
    substeps = max(1, round(period / fine_step))
    step = period / substeps
    t = np.arange(samples * substeps + 1) * step
    owner = np.searchsorted(segment_times[1:-1], t + _BOUNDARY_TOLERANCE, side="right")
    bounds = np.searchsorted(owner, np.arange(len(segments) + 1), side="left")

    speed, heading, yaw_rate, acceleration = (np.empty_like(t) for _ in range(4))
    entry_speed, entry_heading = float(speed0), float(heading0)
    for index, segment in enumerate(segments):
        rows = slice(bounds[index], bounds[index + 1])
        tau = np.clip(t[rows] - segment_times[index], 0.0, segment.duration)
        motion = segment.motion(np.append(tau, segment.duration), entry_speed)
        speed[rows] = motion.speed[:-1]
        heading[rows] = entry_heading + motion.heading_change[:-1]
        yaw_rate[rows] = motion.yaw_rate[:-1]
        acceleration[rows] = motion.acceleration[:-1]
        entry_speed = float(motion.speed[-1])
        entry_heading += float(motion.heading_change[-1])

    cos, sin = np.cos(heading), np.sin(heading)
    vx, vy = speed * cos, speed * sin
    centripetal = speed * yaw_rate
    ax = acceleration * cos - centripetal * sin
    ay = acceleration * sin + centripetal * cos
    x = start[0] + _cumulative_trapezoid(vx, step)
    y = start[1] + _cumulative_trapezoid(vy, step)

    sampled = slice(None, None, substeps)
    return Truth(
        t=np.arange(samples + 1) * period,
        x=x[sampled],
        y=y[sampled],
        vx=vx[sampled],
        vy=vy[sampled],
        ax=ax[sampled],
        ay=ay[sampled],
        heading=np.asarray(wrap_angle(heading[sampled])),
        yaw_rate=yaw_rate[sampled],
        speed=speed[sampled],
        segment_times=segment_times,
    )


def _cumulative_trapezoid(values: np.ndarray, step: float) -> np.ndarray:
    """Running integral of uniformly spaced ``values``, starting at 0."""
    increments = 0.5 * step * (values[1:] + values[:-1])
    return np.concatenate([[0.0], np.cumsum(increments)])
