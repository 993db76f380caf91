"""Compiled (numba) kernels of the integrity bank (``core.integrity_bank``): its prediction, joint
update, separations and protection level, the same equations as the bank's numpy code written as
loops, and one call for a whole epoch (``bank_epoch``). On 6x6 matrices and a handful of filters numpy
spends its time in per-call overhead (about 180 us an epoch); these take a few microseconds. ``core.integrity_bank`` calls them when the kernels are enabled
(``core.compiled.compiled_enabled``) and keeps its numpy code as the reference."""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.integrity_bank import (
    CONVERGED,
    DROPPABLE,
    FIX_X,
    FIX_XX,
    FIX_XY,
    FIX_Y,
    FIX_YY,
    JERK,
    LEVEL,
    SCALARS,
    STATISTIC,
    TABLE,
    TEST_FAILED,
    THRESHOLD,
    UPDATE_FAILED,
    WORST,
)
from edgepos.core.kernels_base import FAILED, OK, IntArray, _jit
from edgepos.core.numerics import FloatArray

_MIN_DISTANCE = 1e-3  # as the bank's numpy update


@_jit
def bank_update(
    means: FloatArray,
    covs: FloatArray,
    owner: IntArray,
    positions: FloatArray,
    observed: FloatArray,
    range_std: FloatArray,
    bearing_std: FloatArray,
) -> int:
    """In place: every filter k updated with the RSUs at ``positions`` (n, 2) whose range and bearing
    (from the RSU to the vehicle) are ``observed`` (n, 2) with standard deviations ``range_std`` and
    ``bearing_std`` (n,), but those whose ``owner`` is k (the sub-filter that leaves the RSU out; -1
    for none), linearised at the reference's (row 0) mean.
    Returns OK, or FAILED (nothing written) when a result is not finite (the caller then runs the numpy
    reference).

    The same update as the numpy reference's stacked one, in the position's information form: H acts on
    x and y only and R is diagonal, so RSU j adds J_j = H_j^T R_j^-1 H_j (2x2) and g_j = H_j^T R_j^-1 r_j
    (r_j its residual at the reference), and with C the filter's position covariance, Cx its columns
    for x and y, and o its position's offset from the reference's (the linearisation point),
    J = sum J_j, g = sum g_j - J o, M = (I + J C)^-1 give m += Cx M g and P -= Cx M J Cx^T (Woodbury:
    the Kalman gain over the stacked rows, without their 2n x 2n innovation covariance)."""
    measurements = positions.shape[0]
    return _update(
        means,
        covs,
        owner,
        positions,
        observed,
        range_std,
        bearing_std,
        np.empty((measurements, 3)),
        np.empty((measurements, 2)),
        np.empty_like(means),
        np.empty_like(covs),
    )


@_jit
def _update(
    means: FloatArray,
    covs: FloatArray,
    owner: FloatArray | IntArray,
    positions: FloatArray,
    observed: FloatArray,
    range_std: FloatArray,
    bearing_std: FloatArray,
    information: FloatArray,
    score: FloatArray,
    new_means: FloatArray,
    new_covs: FloatArray,
) -> int:
    """``bank_update`` with its scratch given: ``information`` (n, 3) for J_j as xx, xy, yy, ``score``
    (n, 2) for g_j, ``new_means`` and ``new_covs`` shaped as the bank's (every element written before
    they are copied back)."""
    count = means.shape[0]
    measurements = positions.shape[0]
    for j in range(measurements):
        dx = means[0, 0] - positions[j, 0]
        dy = means[0, 3] - positions[j, 1]
        distance = max(math.hypot(dx, dy), _MIN_DISTANCE)
        r2 = distance * distance
        rx, ry = dx / distance, dy / distance  # d range / d(x, y)
        bx, by = -dy / r2, dx / r2  # d bearing / d(x, y)
        wr = 1.0 / (range_std[j] * range_std[j])
        wb = 1.0 / (bearing_std[j] * bearing_std[j])
        range_residual = observed[j, 0] - distance
        bearing_residual = (observed[j, 1] - math.atan2(dy, dx) + math.pi) % (2.0 * math.pi) - math.pi
        information[j, 0] = wr * rx * rx + wb * bx * bx
        information[j, 1] = wr * rx * ry + wb * bx * by
        information[j, 2] = wr * ry * ry + wb * by * by
        score[j, 0] = wr * rx * range_residual + wb * bx * bearing_residual
        score[j, 1] = wr * ry * range_residual + wb * by * bearing_residual
    for k in range(count):
        ja = jb = jd = ga = gb = 0.0
        for j in range(measurements):
            if owner[j] != k:
                ja += information[j, 0]
                jb += information[j, 1]
                jd += information[j, 2]
                ga += score[j, 0]
                gb += score[j, 1]
        ox = means[k, 0] - means[0, 0]
        oy = means[k, 3] - means[0, 3]
        ga -= ja * ox + jb * oy
        gb -= jb * ox + jd * oy
        ca, cb, cd = covs[k, 0, 0], 0.5 * (covs[k, 0, 3] + covs[k, 3, 0]), covs[k, 3, 3]
        # I + J C and its inverse (2x2)
        a11 = 1.0 + ja * ca + jb * cb
        a12 = ja * cb + jb * cd
        a21 = jb * ca + jd * cb
        a22 = 1.0 + jb * cb + jd * cd
        det = a11 * a22 - a12 * a21
        if not det > 0.0:
            return FAILED
        i11, i12, i21, i22 = a22 / det, -a12 / det, -a21 / det, a11 / det
        # v = M g; W = M J (symmetric: (C + J^-1)^-1 when J is regular)
        v0, v1 = i11 * ga + i12 * gb, i21 * ga + i22 * gb
        w11 = i11 * ja + i12 * jb
        w12 = i11 * jb + i12 * jd
        w21 = i21 * ja + i22 * jb
        w22 = i21 * jb + i22 * jd
        w12 = w21 = 0.5 * (w12 + w21)
        for i in range(6):
            new_means[k, i] = means[k, i] + covs[k, i, 0] * v0 + covs[k, i, 3] * v1
        for i in range(6):
            xi, yi = covs[k, i, 0], covs[k, i, 3]
            ui = xi * w11 + yi * w21  # (Cx W)[i, 0]
            vi = xi * w12 + yi * w22  # (Cx W)[i, 1]
            for m in range(i, 6):
                value = 0.5 * (covs[k, i, m] + covs[k, m, i]) - (ui * covs[k, m, 0] + vi * covs[k, m, 3])
                new_covs[k, i, m] = value
                new_covs[k, m, i] = value
    for k in range(count):
        for i in range(6):
            if not math.isfinite(new_means[k, i]):
                return FAILED
    means[:, :] = new_means
    covs[:, :, :] = new_covs
    return OK


@_jit
def _separation(means: FloatArray, covs: FloatArray, k: int) -> float:
    """sqrt(q_k) of sub-filter k against the reference (row 0): its position's separation in units of the
    separation's covariance P_k - P_0; 0 while that is singular, as right after the sub-filter starts."""
    dx = means[k, 0] - means[0, 0]
    dy = means[k, 3] - means[0, 3]
    a = covs[k, 0, 0] - covs[0, 0, 0]
    b = covs[k, 0, 3] - covs[0, 0, 3]
    c = covs[k, 3, 3] - covs[0, 3, 3]
    det = a * c - b * b
    if a > 0.0 and c > 0.0 and det > 1e-12 * a * c:
        return math.sqrt(max((c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / det, 0.0))
    return 0.0


@_jit
def bank_separations(means: FloatArray, covs: FloatArray, out: FloatArray) -> None:
    """Per sub-filter k >= 1, into out[k - 1]: sqrt(q_k) (0 while P_k - P_0 is singular), x, y and the
    position covariance's xx, xy, yy; as the bank's numpy ``separations``."""
    for k in range(1, means.shape[0]):
        out[k - 1, 0] = _separation(means, covs, k)
        out[k - 1, 1] = means[k, 0]
        out[k - 1, 2] = means[k, 3]
        out[k - 1, 3] = covs[k, 0, 0]
        out[k - 1, 4] = covs[k, 0, 3]
        out[k - 1, 5] = covs[k, 3, 3]


@_jit
def bank_predict(means: FloatArray, covs: FloatArray, dt: float, jerk_density: float) -> None:
    """In place: every filter to ``dt`` s later under white jerk of density ``jerk_density`` per axis, as
    the bank's numpy ``predict`` (F m, F C F^T + Q with the constant-acceleration F and Q per axis)."""
    _predict(means, covs, dt, jerk_density, np.zeros((6, 6)))


@_jit
def _predict(
    means: FloatArray, covs: FloatArray, dt: float, jerk_density: float, product: FloatArray
) -> None:
    """``bank_predict`` with its scratch given: ``product`` (6x6) for F C.

    F is block diagonal, a block [[1, dt, dt^2 / 2], [0, 1, dt], [0, 0, 1]] per axis, and Q has the same
    blocks. Each entry is the sum a dense F C F^T + Q over a block takes, term by term in the same order,
    with F's entries as numbers instead of read from a matrix: its products by 1 dropped (exact) and those
    by 0 kept (0 * c is -0 for a negative c and NaN for an infinite one, which the sum keeps), and Q's
    zeros outside the blocks added too (-0 + 0 is +0). So the results are those of the matrix form to the
    bit, at less than half its cost."""
    dt2, dt3 = dt * dt, dt * dt * dt
    half = 0.5 * dt2
    q00 = jerk_density * dt2 * dt3 / 20.0
    q01 = jerk_density * dt2 * dt2 / 8.0
    q02 = jerk_density * dt3 / 6.0
    q11 = jerk_density * dt3 / 3.0
    q12 = jerk_density * dt2 / 2.0
    q22 = jerk_density * dt
    for k in range(means.shape[0]):
        for o in (0, 3):
            m0, m1, m2 = means[k, o], means[k, o + 1], means[k, o + 2]
            means[k, o] = m0 + dt * m1 + half * m2
            means[k, o + 1] = 0.0 * m0 + m1 + dt * m2
            means[k, o + 2] = 0.0 * m0 + 0.0 * m1 + m2
            for j in range(6):  # F C: rows o .. o + 2
                c0, c1, c2 = covs[k, o, j], covs[k, o + 1, j], covs[k, o + 2, j]
                product[o, j] = c0 + dt * c1 + half * c2
                product[o + 1, j] = 0.0 * c0 + c1 + dt * c2
                product[o + 2, j] = 0.0 * c0 + 0.0 * c1 + c2
        for i in range(6):
            block = i - i % 3
            for o in (0, 3):  # (F C) F^T + Q: columns o .. o + 2
                p0, p1, p2 = product[i, o], product[i, o + 1], product[i, o + 2]
                n0 = n1 = n2 = 0.0
                if o == block:
                    row = i - o
                    if row == 0:
                        n0, n1, n2 = q00, q01, q02
                    elif row == 1:
                        n0, n1, n2 = q01, q11, q12
                    else:
                        n0, n1, n2 = q02, q12, q22
                covs[k, i, o] = p0 + p1 * dt + p2 * half + n0
                covs[k, i, o + 1] = p0 * 0.0 + p1 + p2 * dt + n1
                covs[k, i, o + 2] = p0 * 0.0 + p1 * 0.0 + p2 + n2


@_jit
def radial_bound(a: float, b: float, d: float, factors: FloatArray) -> float:
    """``core.integrity.radial_bound`` of the 2x2 covariance [[a, b], [b, d]] with the factors tabulated
    for its probability (all zero when the probability needs no bound)."""
    half = 0.5 * (a - d)
    spread = math.sqrt(half * half + b * b)
    largest = 0.5 * (a + d) + spread
    if largest <= 0.0:
        return 0.0
    ratio = min(max((0.5 * (a + d) - spread) / largest, 0.0), 1.0)
    factor: float = factors[math.ceil(ratio * (factors.shape[0] - 1) - 1e-12)]
    return factor * math.sqrt(largest)


@_jit
def bank_protect(
    means: FloatArray,
    covs: FloatArray,
    scalars: FloatArray,
    tables: FloatArray,
    excluded: FloatArray | IntArray,
) -> None:
    """The protection level of the fix from the bank, as ``core.integrity_bank.protect_with_bank``: reads
    the fix (x, y, covariance xx, xy, yy) and the test threshold from ``scalars`` (indices above), the
    fault-free and per-hypothesis radial factors from ``tables`` rows 0 and 1, and whether each filter's
    RSU is excluded already (nonzero) from ``excluded``; writes the level, the index k >= 1 of the worst
    failed test not already excluded (-1: none) and its statistic into ``scalars``. The caller has
    checked the fix's covariance."""
    x, y, threshold = scalars[FIX_X], scalars[FIX_Y], scalars[THRESHOLD]
    level = radial_bound(scalars[FIX_XX], scalars[FIX_XY], scalars[FIX_YY], tables[0])
    offset = math.hypot(x - means[0, 0], y - means[0, 3])
    level = max(level, offset + radial_bound(covs[0, 0, 0], covs[0, 0, 3], covs[0, 3, 3], tables[0]))
    worst, worst_statistic = -1, 0.0
    for k in range(1, means.shape[0]):
        statistic = _separation(means, covs, k)
        if statistic > threshold and excluded[k] == 0 and (worst < 0 or statistic > worst_statistic):
            worst, worst_statistic = k, statistic
        separation = math.hypot(means[k, 0] - x, means[k, 3] - y)
        level = max(level, separation + radial_bound(covs[k, 0, 0], covs[k, 0, 3], covs[k, 3, 3], tables[1]))
    scalars[LEVEL] = level
    scalars[WORST] = worst
    scalars[STATISTIC] = worst_statistic


@_jit
def droppable(means: FloatArray, covs: FloatArray, owner: FloatArray) -> int:
    """How many sub-filters ``SeparationBank.prune`` would drop after this epoch: those no measurement's
    ``owner`` names (their RSU not in use) whose position covariance (trace) exceeds the reference's by
    no more than ``CONVERGED`` of it; the same comparison as prune's, in the same double arithmetic."""
    reference = covs[0, 0, 0] + covs[0, 3, 3]
    bound = CONVERGED * reference
    count = 0
    for k in range(1, means.shape[0]):
        in_use = False
        for j in range(owner.shape[0]):
            if owner[j] == k:
                in_use = True
        if not in_use and not (covs[k, 0, 0] + covs[k, 3, 3]) - reference > bound:
            count += 1
    return count


@_jit
def all_finite(values: FloatArray) -> bool:
    """Whether every value is finite (the bank's decoding checks its arrays)."""
    for value in values:
        if not math.isfinite(value):
            return False
    return True


@_jit
def work_size(measurements: int, filters: int, table: int) -> int:
    """Length of ``bank_epoch``'s ``work`` vector for ``measurements`` RSUs, ``filters`` filters and
    radial factor tables of ``table`` entries (compiled: a run's kernel makes its plans too)."""
    return (
        SCALARS + 2 * table + measurements + filters + 2 + _PREDICT_SCRATCH + 5 * measurements + 42 * filters
    )


_PREDICT_SCRATCH = 36  # bank_predict's F C


@_jit
def bank_epoch(
    means: FloatArray,
    covs: FloatArray,
    work: FloatArray,
    dt: float,
    positions: FloatArray,
    observed: FloatArray,
    range_std: FloatArray,
    bearing_std: FloatArray,
    fix_mean: FloatArray,
    fix_cov: FloatArray,
) -> float:
    """One epoch of the bank in one call: ``bank_predict`` over ``dt`` s (none when it is not positive)
    with ``work[JERK]``, ``bank_update`` with the n RSUs of ``positions`` .. ``bearing_std``,
    the count of sub-filters prune would drop into ``work[DROPPABLE]`` (``droppable``), then the fix read
    from the reported estimate's mean and covariance into ``work`` (``FIX_X`` ..) and ``bank_protect``
    for it. A fix whose position covariance is not positive definite has no bound: the level written is
    NaN (the bank steps on).

    ``work`` holds, after the scalars (``core.integrity_bank``'s indices, ``TABLE`` the length of a radial
    factor table), the fault-free and per-hypothesis tables, then as whole numbers the RSUs' owners (the
    sub-filter that leaves each out, -1: none), per filter 1 if its RSU is excluded already, and the
    indices of x and y in the estimate; then the kernels' scratch (``work_size``). One array for all the
    epoch's constants and temporaries: numba's dispatch costs about a tenth of a microsecond per array
    argument, and an allocation in the kernels about as much.

    Returns the protection level when every test passed (NaN for a fix without a bound), ``TEST_FAILED``
    when one failed (the outcome in ``work``), or ``UPDATE_FAILED`` when the update failed: the bank is
    then predicted, not updated, and no outcome written (the caller finishes the epoch on the numpy
    reference). The level as the return value saves the caller reading it back in the usual epoch."""
    count = positions.shape[0]
    filters = means.shape[0]
    table = int(work[TABLE])
    tables = work[SCALARS : SCALARS + 2 * table].reshape((2, table))
    start = SCALARS + 2 * table  # the owners, the exclusions, x and y
    owner = work[start : start + count]
    excluded = work[start + count : start + count + filters]
    x, y = int(work[start + count + filters]), int(work[start + count + filters + 1])
    scratch = start + count + filters + 2
    if dt > 0.0:
        _predict(
            means,
            covs,
            dt,
            work[JERK],
            work[scratch : scratch + 36].reshape((6, 6)),
        )
    scratch += _PREDICT_SCRATCH
    if count > 0:
        status = _update(
            means,
            covs,
            owner,
            positions,
            observed,
            range_std,
            bearing_std,
            work[scratch : scratch + 3 * count].reshape((count, 3)),
            work[scratch + 3 * count : scratch + 5 * count].reshape((count, 2)),
            work[scratch + 5 * count : scratch + 5 * count + 6 * filters].reshape((filters, 6)),
            work[scratch + 5 * count + 6 * filters : scratch + 5 * count + 42 * filters].reshape(
                (filters, 6, 6)
            ),
        )
        if status != OK:
            return UPDATE_FAILED
    work[DROPPABLE] = droppable(means, covs, owner)
    xx, xy, yy = fix_cov[x, x], fix_cov[x, y], fix_cov[y, y]
    work[FIX_X], work[FIX_Y] = fix_mean[x], fix_mean[y]
    work[FIX_XX], work[FIX_XY], work[FIX_YY] = xx, xy, yy
    if not (xx > 0.0 and yy > 0.0 and xx * yy > xy * xy):  # as core.integrity_bank._proper
        work[LEVEL], work[WORST], work[STATISTIC] = math.nan, -1.0, 0.0
        return math.nan
    bank_protect(means, covs, work, tables, excluded)
    if work[WORST] >= 0.0:
        return TEST_FAILED
    level: float = work[LEVEL]
    return level


def warm_up() -> None:
    """Compile (or load from numba's cache) the signatures the bank calls: a reference and one sub-filter,
    one RSU, with the argument types the bank passes (the owners of ``update_arrays`` read only, all else
    writable). ``core.compiled.warm_up`` calls it."""
    from edgepos.core.integrity import radial_factor_table

    means, covs = np.zeros((2, 6)), np.tile(np.eye(6), (2, 1, 1))
    rsu = (np.array([[0.0, -3.875]]), np.array([[4.0, 1.4]]), np.array([0.6]), np.array([0.01]))
    owners = np.array([1])
    owners.flags.writeable = False
    bank_predict(means, covs, 0.05, 10.0)
    bank_update(means, covs, owners, *rsu)
    bank_separations(means, covs, np.empty((1, 6)))
    tables = np.array([radial_factor_table(5e-6), radial_factor_table(0.05)])
    scalars = np.zeros(SCALARS)
    scalars[JERK], scalars[THRESHOLD] = 10.0, 3.0
    scalars[FIX_XX], scalars[FIX_YY] = 1.0, 1.0
    bank_protect(means, covs, scalars, tables, np.zeros(2, dtype=np.int64))
    table = tables.shape[1]
    work = np.zeros(work_size(1, 2, table))
    work[:SCALARS] = scalars
    work[TABLE] = table
    work[SCALARS : SCALARS + 2 * table] = tables.ravel()
    work[SCALARS + 2 * table : SCALARS + 2 * table + 5] = [1, 0, 0, 0, 3]  # owner, exclusions, x and y
    bank_epoch(means, covs, work, 0.05, *rsu, np.zeros(8), np.eye(8))
    all_finite(np.zeros(6))
