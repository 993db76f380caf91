"""Compiled (numba) kernels of the integrity bank (``core.integrity_bank``): its joint update and its
separations, the same equations as the bank's numpy code written as loops. On 6x6 matrices and a
handful of filters numpy spends its time in per-call overhead (about 180 us an epoch for the two);
these take a few microseconds. ``core.integrity_bank`` calls them when the kernels are enabled
(``core.compiled.compiled_enabled``) and keeps its numpy code as the reference."""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.kernels_base import FAILED, OK, BoolArray, _jit, cholesky
from edgepos.core.numerics import FloatArray

_MIN_DISTANCE = 1e-3  # as the bank's numpy update


@_jit
def bank_update(means: FloatArray, covs: FloatArray, keep: BoolArray, data: FloatArray) -> int:
    """In place: every filter updated with the RSUs of ``data`` (rows: rsu_x, rsu_y, range, bearing,
    range_std, bearing_std) it keeps (``keep[k, j]``), linearised at the reference's (row 0) mean.
    Returns OK, or FAILED (nothing written) when an innovation covariance is not positive definite or
    a result is not finite (the caller then runs the numpy reference)."""
    count, dim = means.shape
    measurements = data.shape[0]
    rows = 2 * measurements
    h = np.zeros((rows, 2))
    residual = np.zeros(rows)
    noise = np.zeros(rows)
    for j in range(measurements):
        dx = means[0, 0] - data[j, 0]
        dy = means[0, 3] - data[j, 1]
        distance = max(math.hypot(dx, dy), _MIN_DISTANCE)
        r2 = distance * distance
        h[2 * j, 0] = dx / distance
        h[2 * j, 1] = dy / distance
        h[2 * j + 1, 0] = -dy / r2
        h[2 * j + 1, 1] = dx / r2
        residual[2 * j] = data[j, 2] - distance
        wrapped = (data[j, 3] - math.atan2(dy, dx) + math.pi) % (2.0 * math.pi)
        residual[2 * j + 1] = wrapped - math.pi
        noise[2 * j] = data[j, 4] * data[j, 4]
        noise[2 * j + 1] = data[j, 5] * data[j, 5]
    new_means = means.copy()
    new_covs = covs.copy()
    hk = np.zeros((rows, 2))
    z = np.zeros(rows)
    pht = np.zeros((dim, rows))
    s = np.zeros((rows, rows))
    factor = np.zeros((rows, rows))
    gain_t = np.zeros((rows, dim))
    for k in range(count):
        ox = means[k, 0] - means[0, 0]
        oy = means[k, 3] - means[0, 3]
        for r in range(rows):
            kept = 1.0 if keep[k, r // 2] else 0.0
            hk[r, 0] = h[r, 0] * kept
            hk[r, 1] = h[r, 1] * kept
            z[r] = (residual[r] - h[r, 0] * ox - h[r, 1] * oy) * kept
        for i in range(dim):
            for r in range(rows):
                pht[i, r] = covs[k, i, 0] * hk[r, 0] + covs[k, i, 3] * hk[r, 1]
        for a in range(rows):
            for b in range(rows):
                s[a, b] = hk[a, 0] * pht[0, b] + hk[a, 1] * pht[3, b]
            s[a, a] += noise[a]
        if not cholesky(s, rows, factor):
            return FAILED
        # gain_t = S^-1 H P (rows x dim), the gain transposed: L Y = H P, then L^T X = Y
        for i in range(dim):
            for r in range(rows):
                total = pht[i, r]
                for c in range(r):
                    total -= factor[r, c] * gain_t[c, i]
                gain_t[r, i] = total / factor[r, r]
            for r in range(rows - 1, -1, -1):
                total = gain_t[r, i]
                for c in range(r + 1, rows):
                    total -= factor[c, r] * gain_t[c, i]
                gain_t[r, i] = total / factor[r, r]
        for i in range(dim):
            total = 0.0
            for r in range(rows):
                total += gain_t[r, i] * z[r]
            new_means[k, i] = means[k, i] + total
        for i in range(dim):
            for m in range(i, dim):
                total = 0.0
                for r in range(rows):
                    total += gain_t[r, i] * pht[m, r] + gain_t[r, m] * pht[i, r]
                value = 0.5 * (covs[k, i, m] + covs[k, m, i]) - 0.5 * total  # (C + C^T) / 2, as numpy's
                new_covs[k, i, m] = value
                new_covs[k, m, i] = value
    for k in range(count):
        for i in range(dim):
            if not math.isfinite(new_means[k, i]):
                return FAILED
    means[:, :] = new_means
    covs[:, :, :] = new_covs
    return OK


@_jit
def bank_separations(means: FloatArray, covs: FloatArray, out: FloatArray) -> None:
    """Per sub-filter k >= 1, into out[k - 1]: sqrt(q_k) (0 while P_k - P_0 is singular), x, y and the
    position covariance's xx, xy, yy; as the bank's numpy ``separations``."""
    for k in range(1, means.shape[0]):
        dx = means[k, 0] - means[0, 0]
        dy = means[k, 3] - means[0, 3]
        a = covs[k, 0, 0] - covs[0, 0, 0]
        b = covs[k, 0, 3] - covs[0, 0, 3]
        c = covs[k, 3, 3] - covs[0, 3, 3]
        det = a * c - b * b
        statistic = 0.0
        if a > 0.0 and c > 0.0 and det > 1e-12 * a * c:
            q = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / det
            statistic = math.sqrt(max(q, 0.0))
        out[k - 1, 0] = statistic
        out[k - 1, 1] = means[k, 0]
        out[k - 1, 2] = means[k, 3]
        out[k - 1, 3] = covs[k, 0, 0]
        out[k - 1, 4] = covs[k, 0, 3]
        out[k - 1, 5] = covs[k, 3, 3]
