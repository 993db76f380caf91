"""The phase differences' displacement fit in a compiled loop (numba): ``fit_kernel``, for ``gnss.tdcp``'s
``_fit`` (weighted least squares with the chi-square exclusions), some twenty numpy calls on (n, 4) arrays
there, each a microsecond or two.

The numpy forms stay the reference (run when ``EDGEPOS_NUMBA=0``; tests hold the kernels to them). The
normal matrix is inverted by Gauss-Jordan elimination with partial pivoting where numpy inverts by LAPACK's
LU and sums run in index order: the numbers agree to about 1e-12 relative (tested) and the rows left out
are the same, but for a tie: with one degree of freedom left every standardised residual is the same, and
rounding picks the row (the epoch then has too few rows either way: no displacement).
"""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.kernels_base import FAILED, OK, _jit
from edgepos.core.numerics import FloatArray

INCONSISTENT = 2
"""``fit_kernel``: fewer than the minimum rows left consistent."""
_UNKNOWNS = 4


@_jit
def _invert(normal: FloatArray, out: FloatArray, max_condition: float) -> bool:
    """``out`` = inverse of the 4 x 4 ``normal`` (Gauss-Jordan, partial pivoting); False when singular or its
    infinity-norm condition number is beyond ``max_condition`` (``gnss.tdcp``'s test)."""
    work = normal.copy()
    for i in range(_UNKNOWNS):
        for j in range(_UNKNOWNS):
            out[i, j] = 1.0 if i == j else 0.0
    for column in range(_UNKNOWNS):
        pivot = column
        for row in range(column + 1, _UNKNOWNS):
            if abs(work[row, column]) > abs(work[pivot, column]):
                pivot = row
        if work[pivot, column] == 0.0 or not math.isfinite(work[pivot, column]):
            return False
        if pivot != column:
            for j in range(_UNKNOWNS):
                work[column, j], work[pivot, j] = work[pivot, j], work[column, j]
                out[column, j], out[pivot, j] = out[pivot, j], out[column, j]
        scale = 1.0 / work[column, column]
        for j in range(_UNKNOWNS):
            work[column, j] *= scale
            out[column, j] *= scale
        for row in range(_UNKNOWNS):
            if row != column:
                factor = work[row, column]
                if factor != 0.0:
                    for j in range(_UNKNOWNS):
                        work[row, j] -= factor * work[column, j]
                        out[row, j] -= factor * out[column, j]
    largest, largest_inverse = 0.0, 0.0
    for i in range(_UNKNOWNS):
        total, total_inverse = 0.0, 0.0
        for j in range(_UNKNOWNS):
            if not math.isfinite(out[i, j]):
                return False
            total += abs(normal[i, j])
            total_inverse += abs(out[i, j])
        largest, largest_inverse = max(largest, total), max(largest_inverse, total_inverse)
    return largest * largest_inverse <= max_condition


@_jit
def fit_kernel(
    y: FloatArray,
    design: FloatArray,
    std: FloatArray,
    bounds: FloatArray,
    min_rows: int,
    max_condition: float,
    keep: np.ndarray,
    solution: FloatArray,
    cov: FloatArray,
    left_out: FloatArray,
) -> int:
    """``gnss.tdcp._fit``'s loop: weighted least squares of the kept rows (``keep``, bool, all true on entry),
    the chi-square test of the weighted residuals against ``bounds[dof]``, and while it fails the row with the
    largest standardised residual left out (``left_out[row]`` = its residual in metres and sigmas). Returns
    OK (``solution``, ``cov`` set), FAILED (singular geometry) or INCONSISTENT (fewer than ``min_rows``
    left; ``keep`` then holds the rows still in)."""
    n = y.shape[0]
    a = np.empty((n, _UNKNOWNS))
    b = np.empty(n)
    normal = np.empty((_UNKNOWNS, _UNKNOWNS))
    rhs = np.empty(_UNKNOWNS)
    weighted = np.empty(n)
    count = n
    while True:
        for i in range(n):
            root = 1.0 / std[i]
            b[i] = y[i] * root
            for j in range(_UNKNOWNS):
                a[i, j] = design[i, j] * root
        for j in range(_UNKNOWNS):
            rhs[j] = 0.0
            for k in range(_UNKNOWNS):
                normal[j, k] = 0.0
        for i in range(n):
            if keep[i]:
                for j in range(_UNKNOWNS):
                    rhs[j] += a[i, j] * b[i]
                    for k in range(_UNKNOWNS):
                        normal[j, k] += a[i, j] * a[i, k]
        if not _invert(normal, cov, max_condition):
            return FAILED
        for j in range(_UNKNOWNS):
            total = 0.0
            for k in range(_UNKNOWNS):
                total += cov[j, k] * rhs[k]
            solution[j] = total
        statistic = 0.0
        for i in range(n):
            if keep[i]:
                fitted = 0.0
                for j in range(_UNKNOWNS):
                    fitted += a[i, j] * solution[j]
                weighted[i] = b[i] - fitted
                statistic += weighted[i] * weighted[i]
        if statistic <= bounds[count - _UNKNOWNS]:
            return OK
        worst, largest = -1, -1.0
        for i in range(n):
            if keep[i]:
                leverage = 0.0
                for j in range(_UNKNOWNS):
                    for k in range(_UNKNOWNS):
                        leverage += a[i, j] * cov[j, k] * a[i, k]
                standardised = abs(weighted[i]) / math.sqrt(max(1.0 - leverage, 1e-9))
                if standardised > largest:
                    worst, largest = i, standardised
        keep[worst] = False
        left_out[worst, 0] = weighted[worst] * std[worst]
        left_out[worst, 1] = largest
        count -= 1
        if count < min_rows:
            return INCONSISTENT
