"""gnss_tight's solution-separation hypotheses in one compiled loop (numba): the all-in-view solution, every
satellite's leave-one-out downdate, a constellation's lone satellite and every constellation solved again
without their rows, and each hypothesis' test statistic, for ``gnss.raim.separations``; and one round of
the snapshot test's least-squares fit (``snapshot_kernel``, for ``pipelines.gnss_screening.snapshot_test``,
whose numpy round stays its reference the same way); and the protection level's per-hypothesis bounds
(``hypothesis_bound_kernel``, for ``gnss.raim._hypothesis_bound``: the same operations in the same order, so
bit for bit, tested).

The same equations as ``gnss.raim`` (see its docstring; it stays the reference the kernel is tested against,
runs when ``EDGEPOS_NUMBA=0``, and takes every epoch the kernel declines). The numpy form costs some hundred
and fifty calls on (n, 4-7) arrays per epoch, each a few microseconds. Here the normal matrices (symmetric
positive definite: H^T W H plus the prior's information) are inverted by Cholesky where numpy inverts by LU,
and the 2x2 pseudo-inverse of each statistic is taken in closed form where numpy calls ``eigh``: the
separations, covariances and statistics agree to about 1e-12 relative (tested), not bit for bit. A normal
matrix that is not positive definite, or a solution that is not finite, makes the kernel decline (status
FAILED) and the numpy form decides, as before.
"""

from __future__ import annotations

import math
import time

import numpy as np

from edgepos.core.kernels_base import FAILED, OK, _jit
from edgepos.core.numerics import FloatArray
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT


@_jit
def _invert_spd(a: FloatArray, out: FloatArray) -> bool:
    """``out`` = a^-1 for a symmetric positive definite (k, k) ``a`` by its Cholesky factor; False when a
    pivot is not positive or the inverse not finite."""
    k = a.shape[0]
    lower = np.zeros((k, k))
    for i in range(k):
        for j in range(i + 1):
            value = a[i, j]
            for p in range(j):
                value -= lower[i, p] * lower[j, p]
            if i == j:
                if not value > 0.0:
                    return False
                lower[i, i] = math.sqrt(value)
            else:
                lower[i, j] = value / lower[j, j]
    inverse_lower = np.zeros((k, k))  # L^-1, lower triangular
    for i in range(k):
        inverse_lower[i, i] = 1.0 / lower[i, i]
        for j in range(i):
            value = 0.0
            for p in range(j, i):
                value -= lower[i, p] * inverse_lower[p, j]
            inverse_lower[i, j] = value / lower[i, i]
    for i in range(k):
        for j in range(i + 1):
            value = 0.0
            for p in range(i, k):
                value += inverse_lower[p, i] * inverse_lower[p, j]
            if not math.isfinite(value):
                return False
            out[i, j] = value
            out[j, i] = value
    return True


@_jit
def _statistic(s0: float, s1: float, a: float, b: float, d: float) -> float:
    """sqrt(s^T S^+ s) for S = [[a, b], [b, d]] with ``gnss.raim._statistic``'s rank rule: eigenvalues
    below 1e-9 of the largest are left out."""
    half = 0.5 * (a - d)
    spread = math.sqrt(half * half + b * b)
    middle = 0.5 * (a + d)
    top, bottom = middle + spread, middle - spread
    limit = 1e-9 * max(top, 1e-300)
    if not top > limit:
        return 0.0
    if bottom > limit:
        determinant = a * d - b * b
        return math.sqrt((d * s0 * s0 - 2.0 * b * s0 * s1 + a * s1 * s1) / determinant)
    # rank one: the eigenvector of the largest eigenvalue, from the better conditioned of its two forms
    if b == 0.0:
        v0, v1 = (1.0, 0.0) if a >= d else (0.0, 1.0)
    else:
        x0, x1 = b, top - a
        y0, y1 = top - d, b
        if x0 * x0 + x1 * x1 >= y0 * y0 + y1 * y1:
            v0, v1 = x0, x1
        else:
            v0, v1 = y0, y1
        norm = math.sqrt(v0 * v0 + v1 * v1)
        v0, v1 = v0 / norm, v1 / norm
    projected = v0 * s0 + v1 * s1
    return math.sqrt(projected * projected / top)


@_jit
def _subset_solve(
    h: FloatArray,
    w: FloatArray,
    z: FloatArray,
    prior: FloatArray,
    keep: np.ndarray,
    solution: FloatArray,
    covariance: FloatArray,
) -> bool:
    """``gnss.raim._solve``: the weighted least-squares (east, north) ``solution`` (2,) and its 2x2
    ``covariance`` with the rows ``keep`` and the position prior, over the columns some kept row has
    (position, then the clocks left); False when not determined."""
    n, width = h.shape
    columns = np.empty(width, dtype=np.int64)
    count = 3
    columns[0], columns[1], columns[2] = 0, 1, 2
    for c in range(3, width):
        for r in range(n):
            if keep[r] and h[r, c] != 0.0:
                columns[count] = c
                count += 1
                break
    normal = np.zeros((count, count))
    right = np.zeros(count)
    for r in range(n):
        if not keep[r]:
            continue
        for i in range(count):
            weighted = w[r] * h[r, columns[i]]
            right[i] += weighted * z[r]
            for j in range(count):
                normal[i, j] += weighted * h[r, columns[j]]
    for i in range(3):
        for j in range(3):
            normal[i, j] += prior[i, j]
    inverse = np.empty((count, count))
    if not _invert_spd(normal, inverse):
        return False
    d_east = 0.0
    d_north = 0.0
    for j in range(count):
        d_east += inverse[1, j] * right[j]
        d_north += inverse[0, j] * right[j]
    solution[0], solution[1] = d_east, d_north
    covariance[0, 0], covariance[0, 1] = inverse[1, 1], inverse[1, 0]
    covariance[1, 0], covariance[1, 1] = inverse[0, 1], inverse[0, 0]
    return math.isfinite(d_east) and math.isfinite(d_north)


@_jit
def separations_kernel(
    h: FloatArray,
    group: np.ndarray,
    groups: int,
    z: FloatArray,
    w: FloatArray,
    prior: FloatArray,
    separation: FloatArray,
    covariance: FloatArray,
    statistic: FloatArray,
) -> int:
    """The hypotheses of ``gnss.raim.separations`` into ``separation`` (n + G, 2: east, north), its
    ``covariance`` (n + G, 2, 2) and ``statistic`` (n + G,): the n satellites in row order, then, when
    there are G > 1 constellations, each constellation ``0..G-1`` (``group`` (n,) per row, the clock column
    3 + group of ``h``). ``prior``: the position prior's information (3, 3). Returns OK, or FAILED when a
    normal matrix is not positive definite or a solution not finite (the numpy form then decides)."""
    n, width = h.shape
    every = np.ones(n, dtype=np.bool_)
    # the all-in-view solution and covariance (every clock column has its rows: all columns kept)
    for c in range(3, width):
        present = False
        for r in range(n):
            if h[r, c] != 0.0:
                present = True
                break
        if not present:
            return FAILED
    normal = np.zeros((width, width))
    right = np.zeros(width)
    for r in range(n):
        for i in range(width):
            weighted = w[r] * h[r, i]
            right[i] += weighted * z[r]
            for j in range(width):
                normal[i, j] += weighted * h[r, j]
    for i in range(3):
        for j in range(3):
            normal[i, j] += prior[i, j]
    p0 = np.empty((width, width))
    if not _invert_spd(normal, p0):
        return FAILED
    d0 = np.zeros(width)
    for i in range(width):
        for j in range(width):
            d0[i] += p0[i, j] * right[j]
    east0, north0 = d0[1], d0[0]
    h00, h01, h11 = p0[1, 1], p0[1, 0], p0[0, 0]  # P_0's horizontal block, (east, north)
    solution = np.empty(2)
    subset = np.empty((2, 2))
    for j in range(n):
        g_east = 0.0
        g_north = 0.0
        s = 0.0
        fitted = 0.0
        for c in range(width):
            g_c = 0.0
            for p in range(width):
                g_c += p0[c, p] * h[j, p]
            s += h[j, c] * g_c
            fitted += h[j, c] * d0[c]
            if c == 1:
                g_east = g_c
            elif c == 0:
                g_north = g_c
        denominator = 1.0 - w[j] * s
        residual = z[j] - fitted
        if denominator > 1e-9:
            scale = w[j] / denominator
            separation[j, 0] = -g_east * scale * residual
            separation[j, 1] = -g_north * scale * residual
            covariance[j, 0, 0] = scale * g_east * g_east
            covariance[j, 0, 1] = scale * g_east * g_north
            covariance[j, 1, 0] = scale * g_north * g_east
            covariance[j, 1, 1] = scale * g_north * g_north
            statistic[j] = abs(residual) * math.sqrt(scale)
            continue
        # the constellation's only satellite: its clock goes with it
        every[j] = False
        determined = _subset_solve(h, w, z, prior, every, solution, subset)
        every[j] = True
        if not determined:
            return FAILED
        _store(j, solution, subset, east0, north0, h00, h01, h11, separation, covariance, statistic)
    if groups > 1:
        keep = np.empty(n, dtype=np.bool_)
        for k in range(groups):
            for r in range(n):
                keep[r] = group[r] != k
            if not _subset_solve(h, w, z, prior, keep, solution, subset):
                return FAILED
            _store(n + k, solution, subset, east0, north0, h00, h01, h11, separation, covariance, statistic)
    return OK


@_jit
def _store(
    row: int,
    solution: FloatArray,
    subset: FloatArray,
    east0: float,
    north0: float,
    h00: float,
    h01: float,
    h11: float,
    separation: FloatArray,
    covariance: FloatArray,
    statistic: FloatArray,
) -> None:
    """A re-solved hypothesis: its separation from the all-in-view solution, the difference of the two
    covariances (symmetrised) and its statistic."""
    separation[row, 0] = solution[0] - east0
    separation[row, 1] = solution[1] - north0
    a = subset[0, 0] - h00
    d = subset[1, 1] - h11
    b = 0.5 * ((subset[0, 1] - h01) + (subset[1, 0] - h01))
    covariance[row, 0, 0], covariance[row, 0, 1] = a, b
    covariance[row, 1, 0], covariance[row, 1, 1] = b, d
    statistic[row] = _statistic(separation[row, 0], separation[row, 1], a, b, d)


@_jit
def snapshot_kernel(
    receiver: FloatArray,
    satellites: FloatArray,
    pseudorange: FloatArray,
    known: FloatArray,
    std: FloatArray,
    group: np.ndarray,
    keep: np.ndarray,
    out: FloatArray,
) -> int:
    """One round of the snapshot test on the rows ``keep``: ``out`` = (the weighted post-fit residuals'
    chi-square statistic, its degrees of freedom, the position in ``keep`` of the largest standardised
    residual, that residual). Linearised at the ECEF ``receiver`` (Sagnac range), unknowns the position
    and one clock per constellation present (``group`` per row, ascending). Returns OK; FAILED when the
    degrees of freedom are below 2 or the normal matrix is not positive definite (the numpy round
    decides)."""
    count = keep.shape[0]
    groups = 0
    for k in range(count):
        groups = max(groups, group[keep[k]] + 1)
    column = np.full(groups, -1, dtype=np.int64)
    for k in range(count):
        column[group[keep[k]]] = 0
    width = 3
    for g in range(groups):
        if column[g] == 0:
            column[g] = width
            width += 1
    out[1] = count - width
    if count - width < 2:
        return FAILED
    design = np.zeros((count, width))
    residual = np.empty(count)
    root = np.empty(count)
    for k in range(count):
        r = keep[k]
        dx = satellites[r, 0] - receiver[0]
        dy = satellites[r, 1] - receiver[1]
        dz = satellites[r, 2] - receiver[2]
        sagnac = OMEGA_EARTH * (satellites[r, 0] * receiver[1] - satellites[r, 1] * receiver[0])
        geometric = math.sqrt(dx * dx + dy * dy + dz * dz) + sagnac / SPEED_OF_LIGHT
        residual[k] = pseudorange[r] - geometric - known[r]
        design[k, 0], design[k, 1], design[k, 2] = -dx / geometric, -dy / geometric, -dz / geometric
        design[k, column[group[r]]] = 1.0
        root[k] = 1.0 / std[r]
    normal = np.zeros((width, width))
    right = np.zeros(width)
    for k in range(count):
        weight = root[k] * root[k]
        for i in range(width):
            right[i] += design[k, i] * weight * residual[k]
            for j in range(width):
                normal[i, j] += design[k, i] * weight * design[k, j]
    inverse = np.empty((width, width))
    if not _invert_spd(normal, inverse):
        return FAILED
    solution = inverse @ right
    statistic = 0.0
    worst, largest = 0, -1.0
    for k in range(count):
        fitted = 0.0
        leverage = 0.0
        for i in range(width):
            fitted += design[k, i] * solution[i]
            row_inverse = 0.0
            for j in range(width):
                row_inverse += inverse[i, j] * design[k, j]
            leverage += design[k, i] * row_inverse
        leverage *= root[k] * root[k]
        normalised = (residual[k] - fitted) * root[k]
        statistic += normalised * normalised
        standardised = abs(normalised) / math.sqrt(max(1.0 - leverage, 1e-6))
        if standardised > largest:
            worst, largest = k, standardised
    out[0], out[2], out[3] = statistic, worst, largest
    return OK


@_jit
def hypothesis_bound_kernel(
    separation_cov: FloatArray,
    largest: FloatArray,
    covariance: FloatArray,
    threshold: float,
    table_of: np.ndarray,
    tables: FloatArray,
) -> float:
    """The largest over the hypotheses of T sqrt(lmax(S_j)) + R(C + S_j, p_j), ``gnss.raim._hypothesis_bound``
    element by element: ``separation_cov`` (n, 2, 2) the S_j, ``largest`` (n,) their lmax (Python's
    ``math.hypot`` in it, computed by the caller: the C library's differs in the last bit), ``covariance``
    (2, 2) C, ``tables`` (t, L) the radial factor tables and ``table_of`` (n,) each hypothesis' table. Only
    additions, products, divisions and square roots, in the numpy form's order: the same bits. NaN (the
    caller then takes the numpy form) when any input or bound is not finite."""
    last = tables.shape[1] - 1
    best = -math.inf
    for j in range(separation_cov.shape[0]):
        if not math.isfinite(largest[j]):
            return math.nan
        bound = threshold * math.sqrt(max(largest[j], 0.0))
        a = covariance[0, 0] + separation_cov[j, 0, 0]
        b = covariance[0, 1] + separation_cov[j, 0, 1]
        d = covariance[1, 1] + separation_cov[j, 1, 1]
        half = 0.5 * (a - d)
        spread = math.sqrt(half * half + b * b)
        top = 0.5 * (a + d) + spread
        if not math.isfinite(top):
            return math.nan
        if top > 0.0:
            ratio = min(max((0.5 * (a + d) - spread) / top, 0.0), 1.0)
            slot = math.ceil(ratio * last - 1e-12)
            bound = bound + tables[table_of[j], slot] * math.sqrt(top)
        if not math.isfinite(bound):
            return math.nan
        best = max(best, bound)
    return best


def snapshot_round(
    receiver: np.ndarray,
    satellites: np.ndarray,
    pseudorange: np.ndarray,
    known: np.ndarray,
    std: np.ndarray,
    group: np.ndarray,
    keep: np.ndarray,
) -> tuple[float, int, int, float] | None:
    """:func:`snapshot_kernel`'s (statistic, dof, worst position, its standardised residual); None when it
    declines."""
    out = np.zeros(4)
    status = snapshot_kernel(
        np.ascontiguousarray(receiver, dtype=float),
        np.ascontiguousarray(satellites, dtype=float),
        np.ascontiguousarray(pseudorange, dtype=float),
        np.ascontiguousarray(known, dtype=float),
        np.ascontiguousarray(std, dtype=float),
        np.ascontiguousarray(group, dtype=np.int64),
        np.ascontiguousarray(keep, dtype=np.int64),
        out,
    )
    if status != OK:
        return None
    return float(out[0]), int(out[1]), int(out[2]), float(out[3])


def separations(
    h: np.ndarray, group: np.ndarray, groups: int, z: np.ndarray, w: np.ndarray, prior: np.ndarray
) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """:func:`separations_kernel`'s (separation, covariance, statistic) arrays; None when it declines."""
    n = len(z)
    count = n + (groups if groups > 1 else 0)
    separation, covariance, statistic = np.empty((count, 2)), np.empty((count, 2, 2)), np.empty(count)
    status = separations_kernel(
        np.ascontiguousarray(h, dtype=float),
        np.ascontiguousarray(group, dtype=np.int64),
        groups,
        np.ascontiguousarray(z, dtype=float),
        np.ascontiguousarray(w, dtype=float),
        np.ascontiguousarray(prior, dtype=float),
        separation,
        covariance,
        statistic,
    )
    return (separation, covariance, statistic) if status == OK else None


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernels' one signature each; returns the seconds."""
    started = time.perf_counter()
    h = np.array([[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 1.0], [0.0, 0.0, 1.0, 1.0], [0.5, 0.5, 0.5, 1.0]])
    separations(h, np.zeros(4, dtype=np.int64), 1, np.zeros(4), np.ones(4), np.eye(3))
    satellites = np.array([[2.0e7, 1.0e7, 1.5e7], [-1.5e7, 2.0e7, 1.0e7], [1.0e7, -2.0e7, 1.5e7]] * 3)
    snapshot_round(
        np.array([4.0e6, 1.0e5, 4.9e6]),
        satellites,
        np.full(9, 2.2e7),
        np.zeros(9),
        np.ones(9),
        np.zeros(9, dtype=np.int64),
        np.arange(9),
    )
    hypothesis_bound_kernel(
        np.ones((2, 2, 2)), np.ones(2), np.eye(2), 1.0, np.zeros(2, dtype=np.int64), np.ones((1, 3))
    )
    return time.perf_counter() - started
