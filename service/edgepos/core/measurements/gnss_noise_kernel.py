"""The pseudorange noise model's per-epoch numbers in compiled loops (numba):

* the noise level's fit (``scale_kernel``): the weighted least-squares fit of the update's rows, their
  studentised squared residuals, the rank-one downdate without the worst row, and the two medians
  ``gnss.noise_level.epoch_scale`` compares (data snooping);
* the correlation factor (``honesty_kernel``): ``pipelines.gnss_correlation.honesty``'s consider
  covariance of the epoch's weighted solution under the Gauss-Markov error model
  (``gnss.error_correlation``: ``honest_factor``, ``averaged_variance``, ``mean_variance``) and the
  Gaussian-update bound;
* the fuzzy noise factor (``fuzzy_factor_kernel``, for ``core.fuzzy.FuzzyNoise.factor``): memberships,
  Table 1's rules and the weighted mean per satellite, only minima, maxima, sums, products and quotients in
  the numpy form's order, so the same bits (tested).

The same equations as the numpy forms (they stay the reference the kernels are tested against, run when
``EDGEPOS_NUMBA=0``, and take every epoch a kernel declines); some forty numpy calls on (n, 4-7) arrays
each there. The normal matrices are inverted by Cholesky where numpy inverts by LU, sums run in index order
and powers are the C library's: the numbers agree to about 1e-12 relative (tested), and the medians are the
same order statistics.
"""

from __future__ import annotations

import math
import time

import numpy as np

from edgepos.core.kernels_base import FAILED, OK, _jit
from edgepos.core.measurements.gnss_raim_kernel import _invert_spd
from edgepos.core.numerics import FloatArray


@_jit
def _median(values: FloatArray, count: int) -> float:
    """numpy's median of ``values[:count]``: the middle one, or the mean of the middle two."""
    ordered = np.sort(values[:count])
    half = count // 2
    if count % 2:
        return float(ordered[half])
    return float((ordered[half - 1] + ordered[half]) / 2.0)


@_jit
def scale_kernel(jacobian: FloatArray, residuals: FloatArray, variance: FloatArray, out: FloatArray) -> int:
    """``out`` = (median of the studentised squares, their count, median of the others' squares after the
    downdate without the worst row, their count, the worst row's square); counts 0 where there is none.
    Returns OK, or FAILED when the normal matrix is not positive definite (the numpy form decides)."""
    rows, unknowns = jacobian.shape
    out[:] = 0.0
    normal = np.zeros((unknowns, unknowns))
    right = np.zeros(unknowns)
    for r in range(rows):
        for i in range(unknowns):
            weighted = jacobian[r, i] / variance[r]
            right[i] += weighted * residuals[r]
            for j in range(unknowns):
                normal[i, j] += weighted * jacobian[r, j]
    inverse = np.empty((unknowns, unknowns))
    if not _invert_spd(normal, inverse):
        return FAILED
    solution = inverse @ right
    post_fit = np.empty(rows)
    leverage = np.empty(rows)
    for r in range(rows):
        fitted = 0.0
        value = 0.0
        for i in range(unknowns):
            fitted += jacobian[r, i] * solution[i]
            row_inverse = 0.0
            for j in range(unknowns):
                row_inverse += inverse[i, j] * jacobian[r, j]
            value += jacobian[r, i] / variance[r] * row_inverse
        post_fit[r] = residuals[r] - fitted
        leverage[r] = value
    squares = np.empty(rows)
    count = 0
    worst, largest = -1, -math.inf
    for r in range(rows):
        remaining = 1.0 - leverage[r]
        if remaining > 1e-9:  # a row the fit must pass through says nothing about the noise
            squares[count] = post_fit[r] * post_fit[r] / (variance[r] * remaining)
            if squares[count] > largest:
                worst, largest = r, squares[count]
            count += 1
    if count == 0:
        return OK
    out[0], out[1] = _median(squares, count), count
    if rows - 1 <= unknowns or count != rows:
        return OK
    out[4] = largest
    remaining = 1.0 - leverage[worst]
    others = np.empty(rows)
    kept = 0
    for r in range(rows):
        if r == worst:
            continue
        coupling = 0.0
        for i in range(unknowns):
            for j in range(unknowns):
                coupling += jacobian[r, i] * inverse[i, j] * jacobian[worst, j]
        pull = coupling / (variance[worst] * remaining)
        moved = post_fit[r] + pull * post_fit[worst]
        spared = 1.0 - (leverage[r] + coupling * pull / variance[r])
        if spared > 1e-9:
            others[kept] = moved * moved / (variance[r] * spared)
            kept += 1
    if kept:
        out[2], out[3] = _median(others, kept), kept
    return OK


@_jit
def _mean_variance(n: float, rho: float) -> float:
    """``gnss.error_correlation.mean_variance`` of one count and correlation."""
    count = max(n, 1.0)
    eps = 1.0 - min(rho, 1.0)
    if count * eps >= 1e-4:
        r = 1.0 - eps
        out = (1.0 + 2.0 * r / eps - 2.0 * r * (1.0 - r**count) / (count * eps**2)) / count
    else:
        out = 1.0 - eps * (count**2 - 1.0) / (3.0 * count)
    return float(min(max(out, 0.0), 1.0))


NO_FACTOR = 2
"""``honesty_kernel``'s status when the rows fix no position (the factor is 1, no bound)."""


@_jit
def honesty_kernel(
    jacobian: FloatArray,
    variance: FloatArray,
    scale: FloatArray,
    count: FloatArray,
    prior: FloatArray,
    tau_s: float,
    fraction: float,
    dt: float,
    out: FloatArray,
) -> int:
    """``out`` = (factor, memory, the epoch's own north-east covariance (nn, ne, ee), the bound's (nn, ne,
    en, ee), 1 when the bound exists) for the rows of ``jacobian`` with model variances ``variance``, raw-code
    variances ``scale``, smoothing counts ``count`` and the prediction's north-east covariance ``prior``.
    Returns OK, NO_FACTOR (``honest_factor`` gives None), or FAILED (the numpy form decides)."""
    rows, unknowns = jacobian.shape
    out[:] = 0.0
    normal = np.zeros((unknowns, unknowns))
    for r in range(rows):
        for i in range(unknowns):
            weighted = jacobian[r, i] / variance[r]
            for j in range(unknowns):
                normal[i, j] += weighted * jacobian[r, j]
    inverse = np.empty((unknowns, unknowns))
    if not _invert_spd(normal, inverse):
        return FAILED
    own = inverse[0, 0] + inverse[1, 1]
    if not math.isfinite(own) or own <= 0.0:
        return NO_FACTOR
    memory = 1.0 + own / (prior[0, 0] + prior[1, 1])
    rho = math.exp(-max(dt, 0.0) / tau_s) if tau_s > 0.0 else 0.0
    true = 0.0
    for r in range(rows):
        n = max(count[r], 1.0)
        overlap = 1.0 - 1.0 / n
        correlated = fraction * _mean_variance(n, rho)
        white = (1.0 - fraction) / n
        averaged = memory * (
            white * _mean_variance(memory, overlap) + correlated * _mean_variance(memory, max(rho, overlap))
        )
        north = 0.0
        east = 0.0
        for j in range(unknowns):
            north += inverse[0, j] * jacobian[r, j]
            east += inverse[1, j] * jacobian[r, j]
        north /= variance[r]
        east /= variance[r]
        true += (north * north + east * east) * (scale[r] * averaged)
    out[0], out[1] = true / own, memory
    a, b, d = inverse[0, 0], 0.5 * (inverse[0, 1] + inverse[1, 0]), inverse[1, 1]
    out[2], out[3], out[4] = a, b, d
    # inv(inv(P) + inv(A)) in closed form (2x2)
    det_p = prior[0, 0] * prior[1, 1] - prior[0, 1] * prior[1, 0]
    det_a = a * d - inverse[0, 1] * inverse[1, 0]
    if det_p == 0.0 or det_a == 0.0:
        return OK
    s00 = prior[1, 1] / det_p + d / det_a
    s01 = -prior[0, 1] / det_p - inverse[0, 1] / det_a
    s10 = -prior[1, 0] / det_p - inverse[1, 0] / det_a
    s11 = prior[0, 0] / det_p + a / det_a
    det_s = s00 * s11 - s01 * s10
    if det_s == 0.0:
        return OK
    out[5], out[6], out[7], out[8] = s11 / det_s, -s01 / det_s, -s10 / det_s, s00 / det_s
    out[9] = 1.0
    return OK


def honesty_numbers(
    jacobian: np.ndarray,
    variance: np.ndarray,
    scale: np.ndarray,
    count: np.ndarray,
    prior: np.ndarray,
    tau_s: float,
    fraction: float,
    dt: float,
) -> tuple[float, float, FloatArray | None] | None:
    """:func:`honesty_kernel` as (factor, memory, bound or None); (1, 1, None) when the rows fix no
    position; None when it declines."""
    out = np.empty(10)
    status = honesty_kernel(
        np.ascontiguousarray(jacobian, dtype=float),
        np.ascontiguousarray(variance, dtype=float),
        np.ascontiguousarray(scale, dtype=float),
        np.ascontiguousarray(count, dtype=float),
        np.ascontiguousarray(prior, dtype=float),
        float(tau_s),
        float(fraction),
        float(dt),
        out,
    )
    if status == FAILED:
        return None
    if status == NO_FACTOR:
        return 1.0, 1.0, None
    bound = np.array([[out[5], out[6]], [out[7], out[8]]]) if out[9] else None
    return float(out[0]), float(out[1]), bound


def epoch_medians(
    jacobian: np.ndarray, residuals: np.ndarray, variance: np.ndarray
) -> tuple[float, int, float, int, float] | None:
    """:func:`scale_kernel`'s five numbers (counts as ints); None when it declines."""
    out = np.empty(5)
    status = scale_kernel(
        np.ascontiguousarray(jacobian, dtype=float),
        np.ascontiguousarray(residuals, dtype=float),
        np.ascontiguousarray(variance, dtype=float),
        out,
    )
    if status != OK:
        return None
    return float(out[0]), int(out[1]), float(out[2]), int(out[3]), float(out[4])


@_jit
def _clip01(value: float) -> float:
    """np.clip(value, 0, 1) of a finite value."""
    return min(max(value, 0.0), 1.0)


@_jit
def fuzzy_factor_kernel(
    elevation: FloatArray,
    cn0: FloatArray,
    breakpoints: FloatArray,
    rules: np.ndarray,
    outputs: FloatArray,
    out: FloatArray,
) -> bool:
    """``out`` (n,): ``FuzzyNoise.factor`` per satellite. ``breakpoints``: elevation low, mid, high (rad),
    C/N0 small, large (dB-Hz); ``rules`` (r, 2): each rule's C/N0 set (0 small, 1 large) and elevation set
    (0 low, 1 mid, 2 high), ``outputs`` (r,) its singleton, in ``fuzzy.RULES``' order (the sums' order).
    False (``out`` incomplete) when an input is not finite: the numpy form decides."""
    low, mid, high, small, large = (
        breakpoints[0],
        breakpoints[1],
        breakpoints[2],
        breakpoints[3],
        breakpoints[4],
    )
    degrees = np.empty(5)
    for i in range(elevation.shape[0]):
        el, c = elevation[i], cn0[i]
        if not (math.isfinite(el) and math.isfinite(c)):
            return False
        rising = _clip01((el - low) / (mid - low))
        upper = _clip01((el - mid) / (high - mid))
        degrees[2] = 1.0 - rising
        degrees[3] = min(rising, 1.0 - upper)
        degrees[4] = upper
        degrees[1] = _clip01((c - small) / (large - small))
        degrees[0] = 1.0 - degrees[1]
        numerator = 0.0
        denominator = 0.0
        for r in range(rules.shape[0]):
            strength = min(degrees[rules[r, 0]], degrees[2 + rules[r, 1]])
            numerator = numerator + strength * outputs[r]
            denominator = denominator + strength
        out[i] = numerator / max(denominator, 1e-12)
    return True


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernels' one signature each; returns the seconds."""
    started = time.perf_counter()
    jacobian = np.array(
        [[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.5, -1.0, 1.0], [-1.0, 0.2, 1.0]]
    )
    epoch_medians(jacobian, np.arange(5.0), np.ones(5))
    honesty_numbers(jacobian, np.ones(5), np.ones(5), np.ones(5), np.eye(2), 58.0, 0.5, 1.0)
    fuzzy_factor_kernel(
        np.full(2, 0.5),
        np.full(2, 40.0),
        np.arange(5.0),
        np.zeros((1, 2), dtype=np.int64),
        np.ones(1),
        np.empty(2),
    )
    return time.perf_counter() - started
