"""The kernels' shared ground: status and kind codes, the state layout, the array types, the numba
decorator and small dense helpers (wrap, Cholesky, symmetrise, finiteness). See ``core.kernels``."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba
import numpy as np
import numpy.typing as npt

from edgepos.core import kernel_cache  # noqa: F401  # imported for its effect: installs the kernels' cache stamps before the first kernel below
from edgepos.core.numerics import FloatArray

OK = 0
FAILED = 1

EKF = 0
SIGMA = 1

LINEAR = 0
TURN = 1

_TINY = 1e-300
_LOG_TWO_PI = math.log(2.0 * math.pi)
_TWO_PI = 2.0 * math.pi
_MIN_DISTANCE = 1e-3  # as core.measurements.rsu: Jacobians below 1 mm are taken at 1 mm
_SMALL_TURN = 1e-4  # as core.motion.turn
_XP, _XV, _XA, _YP, _YV, _YA, _PHI, _OMEGA = range(8)

#: The kernels' other array arguments (float64 states, covariances and scratch are FloatArray).
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

_Function = TypeVar("_Function", bound=Callable[..., Any])


def _jit(function: _Function) -> _Function:
    """njit with an on-disk cache (so no request pays compilation), or in memory when numba finds no
    writable cache directory (next to this file, NUMBA_CACHE_DIR or the user's cache directory):
    the service then compiles at warm-up instead.

    The kernels keep the GIL (no ``nogil``): each runs for microseconds, three times per epoch, and
    releasing the GIL around them let the service's event loop take it at every call, the filter
    thread then waiting up to a switch interval to get it back. Kept, a 20-epoch batch takes one
    hand-off instead of up to sixty; the event loop still preempts the filter thread every switch
    interval (5 ms). Measured: +8 % and +14 % closed-loop epochs/s of a 1-worker service, p99 at 100
    vehicles unchanged. The one exception is a run of epochs (``_jit_nogil``)."""
    # numba ships no types: its dispatcher is called as the function it compiles, so it keeps that
    # function's signature for the type checker.
    return _compiled(function, nogil=False)


def _jit_nogil(function: _Function) -> _Function:
    """``_jit`` releasing the GIL, for ``kernels_run.run_epochs``: one call per batch for a whole run of
    epochs (some 400 us for 20), so one hand-off per batch, while the service's event loop reads,
    validates and answers other requests on the other core. Measured with the light lane on its
    thread: 1.06-1.36 times the epochs/s of the lane on the loop, one worker under wrk
    (docs/benchmarks.md)."""
    return _compiled(function, nogil=True)


def _compiled(function: _Function, nogil: bool) -> _Function:
    """numba's njit of ``function``, cached on disk where numba finds a writable place."""
    try:
        return cast(_Function, numba.njit(cache=True, error_model="numpy", nogil=nogil)(function))
    except RuntimeError:  # "no locator available": nowhere to write the cache
        return cast(_Function, numba.njit(error_model="numpy", nogil=nogil)(function))


# -- small dense helpers -------------------------------------------------------------------------
@_jit
def wrap(angle: float) -> float:
    """Wrap to [-pi, pi), as ``core.numerics.wrap_angle`` (Python's floored modulo)."""
    return (angle + math.pi) % _TWO_PI - math.pi


@_jit
def cholesky(matrix: FloatArray, n: int, out: FloatArray) -> bool:
    """Lower Cholesky factor of matrix[:n, :n] into out[:n, :n]; False when not positive definite."""
    for j in range(n):
        total = matrix[j, j]
        for k in range(j):
            total -= out[j, k] * out[j, k]
        if not total > 0.0:  # also catches NaN
            return False
        diagonal = math.sqrt(total)
        out[j, j] = diagonal
        for i in range(j + 1, n):
            total = matrix[i, j]
            for k in range(j):
                total -= out[i, k] * out[j, k]
            out[i, j] = total / diagonal
        for i in range(j):
            out[i, j] = 0.0
    return True


@_jit
def cholesky_solve(factor: FloatArray, n: int, rhs: FloatArray, work: FloatArray, out: FloatArray) -> None:
    """x with (L L^T) x = rhs for the lower factor L = factor[:n, :n], into out[:n]: forward substitution
    into work[:n], then back substitution (out may be rhs, not work)."""
    for j in range(n):
        value = rhs[j]
        for col in range(j):
            value -= factor[j, col] * work[col]
        work[j] = value / factor[j, j]
    for j in range(n - 1, -1, -1):
        value = work[j]
        for col in range(j + 1, n):
            value -= factor[col, j] * out[col]
        out[j] = value / factor[j, j]


@_jit
def _symmetrize(matrix: FloatArray, n: int) -> None:
    for i in range(n):
        for j in range(i + 1, n):
            value = 0.5 * (matrix[i, j] + matrix[j, i])
            matrix[i, j] = value
            matrix[j, i] = value


@_jit
def _all_finite(array: FloatArray) -> bool:
    total = 0.0
    for value in array.flat:
        total += value
    return math.isfinite(total)


@_jit
def _sinc(x: float) -> float:
    """sin(pi x) / (pi x), exactly 1 at 0."""
    if x == 0.0:
        return 1.0
    y = math.pi * x
    return math.sin(y) / y
