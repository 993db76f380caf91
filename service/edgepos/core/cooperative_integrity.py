"""Fault detection and protection levels for the cooperative pipelines' fixes (GNSS fix + V2V ranges).

One hypothesis per source: the vehicle's own GNSS fix, and each neighbour whose published position a
V2V range was measured against. Each source's information on the horizontal position and its post-fit
residual term go to the snapshot solution separation of ``core.integrity.protect`` (the filter's
posterior less one source's information is the solution without it):

* a GNSS fix z = p + b + v with the bias b's mean and covariance B and white variance w: position
  information (B + w I)^-1 and innovation term (B + w I)^-1 (z - b - x);
* a range rho to a neighbour at q with effective variance s^2 (the range's own variance plus the
  neighbour's position covariance along the line of sight, as the pipeline's update weighted it):
  information u u^T / s^2 and innovation term u (rho - |x - q|) / s^2, u the unit vector from q to x.

A neighbour broadcasting a position wrong by e moves its range by the projection of e on the line of
sight: the test sees that part, and the protection level bounds what an undetected one can do
(Joerger and Pervan 2013; docs/integrity.md, "Cooperative pipelines").

The formulas are ``core.integrity``'s (subset covariance P_i = (P^-1 - J_i)^-1, separation d_i with
covariance P_i - P, q_i = d_i^T (P_i - P)^+ d_i, protection level from the largest of the fault-free
and per-hypothesis bounds) with one change: a range's information has rank 1, so its separation's
covariance is singular and q_i uses the pseudo-inverse (the separation lies along one direction:
q_i is chi-square with 1 degree of freedom, still compared with the 2-dof threshold, which is
conservative for false alarms).

A fault across the line of sight barely changes the range (a 20 m offset at 30 m, 80 degrees off the
line of sight, moves it by 2-5 m, within 2 sigma of a V2V range), so the snapshot test cannot see it.
What the receiver also has is the neighbour's broadcast over time: ``track_step_statistic`` tests each
new step of a published track against the constant-velocity prediction from the point before it.
Consecutive estimates of one filter have positively correlated errors, so the sum of the two
points' position covariances (the earlier one carried forward) plus the prediction's own noise bounds
the step's covariance; a broadcast position that jumps (a wrong map match, a receiver locking on a
reflection) fails it whatever its direction (docs/integrity.md, "Cooperative pipelines").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.core.integrity import (
    ALARM,
    OK,
    UNAVAILABLE,
    IntegrityBudget,
    Matrix2,
    Protection,
    SourceEffect,
    radial_bound,
    test_threshold,
)


@dataclass(frozen=True)
class RangeSource:
    """A V2V range used in an update: the neighbour's point (m, site frame), the range (m) and the
    effective 1-sigma (m) the update gave it."""

    neighbour: str
    point: tuple[float, float]
    measured: float
    std: float


def fix_effect(
    x: float, y: float, fix: tuple[float, float], bias_mean: np.ndarray, bias_cov: np.ndarray, white: float
) -> SourceEffect:
    """A GNSS fix's information and innovation term at the posterior (x, y)."""
    a = float(bias_cov[0, 0]) + white
    b = 0.5 * float(bias_cov[0, 1] + bias_cov[1, 0])
    d = float(bias_cov[1, 1]) + white
    det = a * d - b * b
    ia, ib, id_ = d / det, -b / det, a / det
    rx = fix[0] - float(bias_mean[0]) - x
    ry = fix[1] - float(bias_mean[1]) - y
    return SourceEffect((ia, ib, id_), (ia * rx + ib * ry, ib * rx + id_ * ry))


def range_effect(x: float, y: float, source: RangeSource) -> SourceEffect:
    """A V2V range's information and innovation term at the posterior (x, y)."""
    dx, dy = x - source.point[0], y - source.point[1]
    distance = max(math.hypot(dx, dy), 1e-3)
    ux, uy = dx / distance, dy / distance
    weight = 1.0 / (source.std * source.std)
    residual = source.measured - distance
    return SourceEffect(
        (weight * ux * ux, weight * ux * uy, weight * uy * uy),
        (weight * ux * residual, weight * uy * residual),
    )


def cooperative_protection(
    x: float,
    y: float,
    position_cov: Sequence[Sequence[float]],
    fix: SourceEffect | None,
    ranges: Sequence[RangeSource],
    budget: IntegrityBudget,
    scale: float = 1.0,
) -> Protection:
    """Protection of a fix at (x, y) with posterior position covariance ``position_cov``: the sources
    are the GNSS fix (first, when given) and the ranges; ``Protection.faulty`` indexes that list.
    ``scale``: the filter's consistency scale (see :func:`protect_sources`)."""
    sources = ([fix] if fix is not None else []) + [range_effect(x, y, r) for r in ranges]
    return protect_sources(position_cov, sources, budget, scale)


def _inverse(m: Matrix2) -> Matrix2 | None:
    a, b, d = m
    det = a * d - b * b
    if not (a > 0.0 and d > 0.0 and det > 1e-12 * a * d) or not math.isfinite(det):
        return None
    return (d / det, -b / det, a / det)


def _eigen(m: Matrix2) -> tuple[tuple[float, float], tuple[float, float], float, float]:
    """Unit eigenvectors and eigenvalues (largest first) of a symmetric 2x2 matrix."""
    a, b, d = m
    half = 0.5 * (a - d)
    spread = math.hypot(half, b)
    large, small = 0.5 * (a + d) + spread, 0.5 * (a + d) - spread
    angle = 0.5 * math.atan2(2.0 * b, a - d)
    first = (math.cos(angle), math.sin(angle))
    return first, (-first[1], first[0]), large, small


def separation_statistic(separation: Matrix2, dx: float, dy: float) -> float:
    """sqrt(d^T S^+ d) for a separation d with covariance S, pseudo-inverted below 1e-9 of its largest
    eigenvalue (a rank-1 source's separation has one direction)."""
    first, second, large, small = _eigen(separation)
    if large <= 0.0:
        return 0.0
    q = (first[0] * dx + first[1] * dy) ** 2 / large
    if small > 1e-9 * large:
        q += (second[0] * dx + second[1] * dy) ** 2 / small
    return math.sqrt(q)


def track_step_statistic(
    earlier: tuple[float, float, float, float, float, Sequence[Sequence[float]]],
    later: tuple[float, float, float, Sequence[Sequence[float]]],
    accel_std: float,
) -> float:
    """sqrt(d^T S^-1 d) for the step d from ``earlier`` (t, x, y, vx, vy, 4x4 covariance of
    [x, y, vx, vy]) predicted at constant velocity to ``later`` (t, x, y, its 4x4 covariance): S is
    F P F^T (the earlier point carried forward) + the later point's position covariance + white
    acceleration ``accel_std`` (m/s^2) over the interval. 0 for a step that does not advance in time or
    whose covariance is not positive definite (nothing to test)."""
    t0, x0, y0, vx, vy, p = earlier
    t1, x1, y1, c = later
    dt = t1 - t0
    if not dt > 0.0:
        return 0.0
    noise = accel_std * accel_std * dt**4 / 4.0
    a = p[0][0] + dt * (p[0][2] + p[2][0]) + dt * dt * p[2][2] + c[0][0] + noise
    d = p[1][1] + dt * (p[1][3] + p[3][1]) + dt * dt * p[3][3] + c[1][1] + noise
    b = 0.5 * (
        p[0][1] + p[1][0] + dt * (p[0][3] + p[2][1] + p[1][2] + p[3][0]) + dt * dt * (p[2][3] + p[3][2])
    )
    b += 0.5 * (c[0][1] + c[1][0])
    inverse = _inverse((float(a), float(b), float(d)))
    if inverse is None:
        return 0.0
    ia, ib, id_ = inverse
    dx, dy = x1 - (x0 + vx * dt), y1 - (y0 + vy * dt)
    return math.sqrt(max(ia * dx * dx + 2.0 * ib * dx * dy + id_ * dy * dy, 0.0))


def protect_sources(
    position_cov: Sequence[Sequence[float]],
    sources: Sequence[SourceEffect],
    budget: IntegrityBudget,
    scale: float = 1.0,
) -> Protection:
    """Protection level and fault detection of a posterior with covariance ``position_cov`` (2x2, m^2)
    shaped by ``sources`` of rank 1 or 2 (see the module docstring).

    ``scale`` >= 1 is how much larger than the filter's covariance its error is (``core.consistency``):
    the tests keep the filter's own covariances (a test that passes bounds its separation by T sqrt(lambda)
    whatever the scale, and the fix's exclusions stay those of the filter), while the error bounds of the
    fault-free solution and of each subset solution are those of ``scale`` times their covariance,
    sqrt(scale) times the radius. An infinite ``scale`` (one not yet bounded) leaves the fix unavailable
    without a fault, and still runs the tests: a failed one is an alarm pointing at its source."""
    covariance: Matrix2 = (
        float(position_cov[0][0]),
        0.5 * (float(position_cov[0][1]) + float(position_cov[1][0])),
        float(position_cov[1][1]),
    )
    information = _inverse(covariance)
    if information is None:
        return Protection(None, UNAVAILABLE)
    fault_free_share = 0.5 * budget.integrity_risk
    inflation = math.sqrt(scale)
    level = inflation * radial_bound(covariance, fault_free_share)
    threshold = test_threshold(budget.false_alarm_probability, len(sources)) if sources else 0.0
    missed = fault_free_share / max(len(sources), 1) / budget.fault_probability
    worst: tuple[float, int] | None = None
    ia, ib, id_ = information
    for index, source in enumerate(sources):
        ja, jb, jd = source.information
        subset = _inverse((ia - ja, ib - jb, id_ - jd))
        if subset is None:
            return Protection(None, UNAVAILABLE)  # this source alone fixes a direction: no check
        sa, sb, sd = subset
        gx, gy = source.innovation
        dx, dy = -(sa * gx + sb * gy), -(sb * gx + sd * gy)
        separation: Matrix2 = (sa - covariance[0], sb - covariance[1], sd - covariance[2])
        statistic = separation_statistic(separation, dx, dy)
        if statistic > threshold and (worst is None or statistic > worst[0]):
            worst = (statistic, index)
        spread = max(_eigen(separation)[2], 0.0)
        level = max(level, threshold * math.sqrt(spread) + inflation * radial_bound(subset, missed))
    if not math.isfinite(level):
        if worst is not None:
            return Protection(None, ALARM, faulty=worst[1], statistic=worst[0], threshold=threshold)
        return Protection(None, UNAVAILABLE)
    if worst is not None:
        return Protection(level, ALARM, faulty=worst[1], statistic=worst[0], threshold=threshold)
    return Protection(level, ALARM if level > budget.alert_limit else OK)
