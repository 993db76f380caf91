"""Horizontal protection levels and fault detection by solution separation, in the position domain.

A fix's covariance says how good it is when nothing is wrong. The protection level bounds the
horizontal error at a stated integrity risk when one measurement source (one RSU, one neighbour) may
be faulty, and the same test that sizes the bound detects such a fault (Blanch et al., "Baseline
advanced RAIM user algorithm", ION GNSS 2012, for snapshot solution separation; Joerger and Pervan,
"Kalman filter-based integrity monitoring against sensor faults", JGCD 2013, for its use with a
filter's prior). Here it runs on the filter's posterior, one hypothesis per source:

* The posterior position covariance P (2x2) is the inverse of the position information I = P^-1,
  which is the prior's information plus each source's J_i = H_i^T R_i^-1 H_i (H_i the source's
  Jacobian with respect to the position, linearised at the posterior).
* Without source i the information is I - J_i: the subset solution has covariance
  P_i = (I - J_i)^-1 and lies at x_i = x - P_i H_i^T R_i^-1 r_i (r_i the source's post-fit
  residuals), so the separation d_i = x_i - x has covariance P_i - P when nothing is faulty.
* Test: q_i = d_i^T (P_i - P)^-1 d_i is chi-square with 2 degrees of freedom fault-free; it is
  compared with the (1 - P_FA / N) quantile. A failed test detects a fault in source i.
* Protection level: the largest of the fault-free bound R(P, p_ff) and, per hypothesis, the
  separation's bound T sqrt(lmax(P_i - P)) plus R(P_i, p_i), where lmax is the largest eigenvalue and
  R(C, p) the radius a zero-mean 2-D Gaussian error with covariance C exceeds with probability p (its
  exact radial tail, tabulated by the ratio of C's eigenvalues; between circular, sqrt(-2 ln p), and
  one-dimensional, the two-sided normal quantile, in units of sqrt(lmax)). The integrity risk is split
  evenly between the fault-free case and the fault hypotheses, p_i = (risk / 2 / N) / P_fault; a
  hypothesis whose prior probability is below its share needs no bound beyond its separation.

The model of the filter is linear at the posterior and the prior is taken as fault-free: a fault
that grew below the threshold over earlier epochs is partly in the prior already (the limitation
of every epoch-wise filter monitor: on the RSU + IMU scenario it gave 39 misleading epochs of 16,000,
docs/integrity.md). The ``rsu_imu`` pipeline therefore runs the hypotheses over time instead
(``core.integrity_bank``, which shares this module's radial bound, thresholds and types); ``protect``
is the snapshot form, for sources checked one epoch at a time.

Pure floats: the 2x2 algebra in closed form costs a few microseconds per source, where numpy's
per-call overhead on such small arrays would cost more than the filter step.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.special import erfc
from scipy.stats import chi2

#: Integrity states of a fix, as the wire carries them.
OK, ALARM, UNAVAILABLE = "ok", "alarm", "unavailable"

Matrix2 = tuple[float, float, float]
"""A symmetric 2x2 matrix as (a, b, d): [[a, b], [b, d]]."""


@dataclass(frozen=True, eq=False)
class IntegrityBudget:
    """The risks a session's protection levels are sized to, per epoch (hashed by identity: it keys the
    caches of thresholds and tables every epoch, and sessions share one per option set)."""

    integrity_risk: float
    """Probability that the error exceeds the protection level while the fix is not in alarm."""
    false_alarm_probability: float
    """Probability that a fault-free epoch fails a test (a needless exclusion), split over the tests."""
    fault_probability: float
    """Prior probability that one given source is faulty in an epoch."""
    alert_limit: float
    """A protection level above this (m) puts the fix in alarm."""


@dataclass(frozen=True)
class SourceEffect:
    """One measurement source's information on the position and its post-fit residual term.

    ``information`` is H^T R^-1 H and ``innovation`` is H^T R^-1 r (a 2-vector), both with respect
    to the horizontal position (x, y) in the site frame."""

    information: Matrix2
    innovation: tuple[float, float]


@dataclass(frozen=True)
class Protection:
    """The outcome for one fix: its protection level (m) and integrity state, and the source the
    tests point at (index into the sources given, None when every test passed)."""

    level: float | None
    state: str
    faulty: int | None = None
    statistic: float | None = None
    threshold: float | None = None


_PROTECTION_FIELDS = {"level": None, "state": OK, "faulty": None, "statistic": None, "threshold": None}


def new_protection(level: float | None, state: str) -> Protection:
    """``Protection(level, state)`` without the frozen ``__init__`` (every test passed), for the RSU monitor
    that builds one every epoch: the instance's ``__dict__`` filled from a template gives the same object
    (equal, hashed and pickled alike) in about a third of the time, as ``core.imm.new_gaussian``."""
    protection = object.__new__(Protection)
    fields = protection.__dict__
    fields.update(_PROTECTION_FIELDS)
    fields["level"], fields["state"] = level, state
    return protection


def _inverse(m: Matrix2) -> Matrix2 | None:
    """Inverse of a symmetric positive definite 2x2 matrix; None if it is not one."""
    a, b, d = m
    det = a * d - b * b
    if not (a > 0.0 and d > 0.0 and det > 1e-12 * a * d) or not math.isfinite(det):
        return None
    return (d / det, -b / det, a / det)


def _largest_eigenvalue(m: Matrix2) -> float:
    a, b, d = m
    half = 0.5 * (a - d)
    return 0.5 * (a + d) + math.sqrt(half * half + b * b)


#: Ratios lmin / lmax at which the radial bound is tabulated; a ratio between two is bounded by the
#: upper one's factor (the factor grows with the ratio), so the table never makes a bound smaller.
_RATIOS = np.linspace(0.0, 1.0, 33)
_Z = np.linspace(-12.0, 12.0, 4801)  # z of the minor axis: beyond 12 sigma the density is below 1e-31
_DENSITY = np.exp(-0.5 * _Z * _Z) / math.sqrt(2.0 * math.pi) * (_Z[1] - _Z[0])


def _radial_tail(k: float, ratio: float) -> float:
    """P(z1^2 + ratio z2^2 > k^2) for independent standard normal z1, z2: the probability that a 2-D
    Gaussian error with eigenvalues lmax and ratio * lmax lies beyond k sqrt(lmax) (by quadrature over z2)."""
    rest = np.maximum(k * k - ratio * _Z * _Z, 0.0)
    return float(np.sum(_DENSITY * erfc(np.sqrt(rest / 2.0))))


@functools.lru_cache(maxsize=64)
def _radial_factors(probability: float) -> tuple[float, ...]:
    """For each tabulated ratio, k with P(|e| > k sqrt(lmax)) = probability."""
    factors = []
    for ratio in _RATIOS:
        upper = math.sqrt(-2.0 * math.log(probability)) + 1.0  # the circular case's k bounds every ratio
        factors.append(
            brentq(lambda k, r=float(ratio): _radial_tail(k, r) - probability, 0.0, upper, xtol=1e-9)
        )
    return tuple(factors)


@functools.lru_cache(maxsize=64)
def radial_factor_table(probability: float) -> np.ndarray:
    """The factors ``radial_bound`` uses for ``probability``, one per tabulated eigenvalue ratio, as a
    read-only array for compiled code (all zero when the probability is 1 or more: no bound needed)."""
    table = np.zeros(len(_RATIOS)) if probability >= 1.0 else np.array(_radial_factors(probability))
    table.flags.writeable = False
    return table


def radial_bound(m: Matrix2, probability: float) -> float:
    """R with P(|e| > R) <= probability for a zero-mean 2-D Gaussian e with covariance ``m`` (the exact
    tail of its radial error, tabulated by eigenvalue ratio; 0 when probability >= 1)."""
    if probability >= 1.0:
        return 0.0
    a, b, d = m
    half = 0.5 * (a - d)
    spread = math.sqrt(half * half + b * b)
    largest = 0.5 * (a + d) + spread
    if largest <= 0.0:
        return 0.0
    ratio = min(max((0.5 * (a + d) - spread) / largest, 0.0), 1.0)
    factors = _radial_factors(probability)
    return factors[math.ceil(ratio * (len(factors) - 1) - 1e-12)] * math.sqrt(largest)


@functools.lru_cache(maxsize=256)
def test_threshold(false_alarm_probability: float, tests: int) -> float:
    """Square root of the chi-square (2 dof) quantile each of ``tests`` tests is compared with."""
    return math.sqrt(float(chi2.isf(false_alarm_probability / max(tests, 1), 2)))


def protect(
    position_cov: Sequence[Sequence[float]], sources: Sequence[SourceEffect], budget: IntegrityBudget
) -> Protection:
    """Protection level and fault detection for a posterior with covariance ``position_cov`` (2x2,
    m^2) shaped by ``sources``; see the module docstring for the formulas."""
    covariance: Matrix2 = (
        float(position_cov[0][0]),
        0.5 * (float(position_cov[0][1]) + float(position_cov[1][0])),
        float(position_cov[1][1]),
    )
    information = _inverse(covariance)
    if information is None:
        return Protection(None, UNAVAILABLE)
    fault_free_share = 0.5 * budget.integrity_risk
    level = radial_bound(covariance, fault_free_share)
    threshold = test_threshold(budget.false_alarm_probability, len(sources)) if sources else 0.0
    per_hypothesis = fault_free_share / max(len(sources), 1)
    missed = per_hypothesis / budget.fault_probability
    worst: tuple[float, int] | None = None
    for index, hypothesis in enumerate(_hypotheses(covariance, information, sources)):
        if hypothesis is None:
            return Protection(None, UNAVAILABLE)  # this source alone fixes a direction: no check
        statistic, separation, subset = hypothesis
        if statistic > threshold and (worst is None or statistic > worst[0]):
            worst = (statistic, index)
        bound = threshold * math.sqrt(_largest_eigenvalue(separation)) + radial_bound(subset, missed)
        level = max(level, bound)
    if not math.isfinite(level):
        return Protection(None, UNAVAILABLE)
    if worst is not None:
        return Protection(level, ALARM, faulty=worst[1], statistic=worst[0], threshold=threshold)
    return Protection(level, ALARM if level > budget.alert_limit else OK)


def _hypotheses(
    covariance: Matrix2, information: Matrix2, sources: Sequence[SourceEffect]
) -> list[tuple[float, Matrix2, Matrix2] | None]:
    """Per source: the separation statistic sqrt(q_i), the separation's covariance P_i - P and the subset
    covariance P_i; None for a source without which the position is not determined."""
    a, b, d = covariance
    ia, ib, id_ = information
    out: list[tuple[float, Matrix2, Matrix2] | None] = []
    for source in sources:
        ja, jb, jd = source.information
        subset = _inverse((ia - ja, ib - jb, id_ - jd))
        if subset is None:
            out.append(None)
            continue
        sa, sb, sd = subset
        gx, gy = source.innovation
        dx, dy = -(sa * gx + sb * gy), -(sb * gx + sd * gy)
        separation: Matrix2 = (sa - a, sb - b, sd - d)
        inverse_separation = _inverse(separation)
        if inverse_separation is None:  # a source that adds no information cannot move the solution
            out.append((0.0, (0.0, 0.0, 0.0), subset))
            continue
        pa, pb, pd = inverse_separation
        out.append(
            (math.sqrt(max(dx * (pa * dx + pb * dy) + dy * (pb * dx + pd * dy), 0.0)), separation, subset)
        )
    return out


def separation_statistics(
    position_cov: Sequence[Sequence[float]], sources: Sequence[SourceEffect]
) -> list[float]:
    """sqrt(q_i) of every source (chi-square with 2 degrees of freedom when nothing is faulty); NaN for
    a source without which the position is not determined."""
    covariance: Matrix2 = (float(position_cov[0][0]), float(position_cov[0][1]), float(position_cov[1][1]))
    information = _inverse(covariance)
    if information is None:
        return [math.nan] * len(sources)
    return [math.nan if h is None else h[0] for h in _hypotheses(covariance, information, sources)]


def range_bearing_effect(
    x: float,
    y: float,
    rsu_x: float,
    rsu_y: float,
    measured_range: float,
    measured_bearing: float,
    range_std: float,
    bearing_std: float,
) -> SourceEffect:
    """An RSU's range and bearing (from the RSU to the vehicle, rad) at the posterior (x, y)."""
    dx, dy = x - rsu_x, y - rsu_y
    distance = max(math.hypot(dx, dy), 1e-3)
    r2 = distance * distance
    # rows of H: d range / d(x, y) = (dx, dy) / r; d bearing / d(x, y) = (-dy, dx) / r^2
    hr = (dx / distance, dy / distance)
    hb = (-dy / r2, dx / r2)
    wr, wb = 1.0 / (range_std * range_std), 1.0 / (bearing_std * bearing_std)
    range_residual = measured_range - distance
    bearing_residual = math.remainder(measured_bearing - math.atan2(dy, dx), math.tau)
    information = (
        wr * hr[0] * hr[0] + wb * hb[0] * hb[0],
        wr * hr[0] * hr[1] + wb * hb[0] * hb[1],
        wr * hr[1] * hr[1] + wb * hb[1] * hb[1],
    )
    innovation = (
        wr * hr[0] * range_residual + wb * hb[0] * bearing_residual,
        wr * hr[1] * range_residual + wb * hb[1] * bearing_residual,
    )
    return SourceEffect(information, innovation)
