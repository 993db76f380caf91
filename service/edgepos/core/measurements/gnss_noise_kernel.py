"""The noise level's per-epoch fit in one compiled loop (numba): the weighted least-squares fit of the
update's rows, their studentised squared residuals, the rank-one downdate without the worst row, and the
two medians ``gnss.noise_level.epoch_scale`` compares (data snooping).

The same equations as ``gnss.noise_level`` (it stays the reference the kernel is tested against, runs
when ``EDGEPOS_NUMBA=0``, and takes every epoch the kernel declines); some forty numpy calls on (n, 4-7)
arrays there. The normal matrix is inverted by Cholesky where numpy inverts by LU: the squares agree to
about 1e-12 relative (tested), and the medians are the same order statistics of them.
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


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernel's one signature; returns the seconds."""
    started = time.perf_counter()
    jacobian = np.array(
        [[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.5, -1.0, 1.0], [-1.0, 0.2, 1.0]]
    )
    epoch_medians(jacobian, np.arange(5.0), np.ones(5))
    return time.perf_counter() - started
