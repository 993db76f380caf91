"""The UPF's importance weights in one compiled loop (numba): each particle's measurement log-likelihood (the
Gaussian or the inlier/outlier mixture of ``base.Measurement``), its prior and proposal log-densities under
the covariance factors all particles share, and the normalisation, instead of some twenty numpy calls on
(N, m) and (N, k) arrays (``Measurement.log_likelihood``, two ``base.gaussian_logpdf`` and
``base.normalise``, which stay the reference the kernel is tested against and run with ``EDGEPOS_NUMBA=0``
or when the particles have covariances of their own).

The loop's sums run in index order where numpy's run pairwise, and its exp and log1p are the C library's
where numpy's are its SIMD ones: the weights agree to a few units in the last place (tested), not bit for
bit.
"""

from __future__ import annotations

import math
import time

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.errors import NumericalError
from edgepos.core.kernels_base import _jit
from edgepos.core.numerics import FloatArray
from edgepos.core.particles.base import Measurement

_LOG_2PI = math.log(2.0 * math.pi)
_LOG_2 = math.log(2.0)


@_jit
def _logaddexp(x: float, y: float) -> float:
    """log(exp(x) + exp(y)) as numpy's ``logaddexp`` computes it."""
    if x == y:
        return x + _LOG_2
    tmp = x - y
    if tmp > 0.0:
        return x + math.log1p(math.exp(-tmp))
    if tmp <= 0.0:
        return y + math.log1p(math.exp(tmp))
    return tmp


@_jit
def _whitened_norm(chol: FloatArray, deviation: FloatArray, i: int, work: FloatArray) -> float:
    """|L^-1 d|^2 for row ``i`` of ``deviation`` by forward substitution (``work`` (k,) scratch)."""
    k = chol.shape[0]
    total = 0.0
    for a in range(k):
        value = deviation[i, a]
        for b in range(a):
            value -= chol[a, b] * work[b]
        value /= chol[a, a]
        work[a] = value
        total += value * value
    return total


@_jit
def log_weights_kernel(
    previous: FloatArray,
    residual: FloatArray,
    mixture: FloatArray,
    variances: FloatArray,
    outliers: bool,
    prior_deviation: FloatArray,
    prior_chol: FloatArray,
    proposal_deviation: FloatArray,
    proposal_chol: FloatArray,
    out: FloatArray,
) -> float:
    """``out`` (N,) = previous + log p(z | x) + log N(prior deviation; 0, P) - log N(proposal deviation; 0,
    P_post), normalised so the weights sum to one; returns the largest unnormalised log-weight (not finite:
    every particle lost, ``out`` left unnormalised). ``mixture`` (4, m): ``Measurement._mixture``'s inlier
    scale and offset, outlier scale and offset, read when ``outliers``; else the Gaussian of ``variances``."""
    count, m = residual.shape
    k = prior_chol.shape[0]
    log_det_prior = 0.0
    log_det_proposal = 0.0
    for a in range(k):
        log_det_prior += math.log(prior_chol[a, a])
        log_det_proposal += math.log(proposal_chol[a, a])
    constant = 0.5 * k * _LOG_2PI
    work = np.empty(k)
    top = -math.inf
    for i in range(count):
        likelihood = 0.0
        if outliers:
            for j in range(m):
                squared = residual[i, j] * residual[i, j]
                likelihood += _logaddexp(
                    squared * mixture[0, j] + mixture[1, j], squared * mixture[2, j] + mixture[3, j]
                )
        else:
            for j in range(m):
                likelihood += (
                    residual[i, j] * residual[i, j] / variances[j] + math.log(variances[j]) + _LOG_2PI
                )
            likelihood *= -0.5
        prior = -0.5 * _whitened_norm(prior_chol, prior_deviation, i, work) - log_det_prior - constant
        proposal = (
            -0.5 * _whitened_norm(proposal_chol, proposal_deviation, i, work) - log_det_proposal - constant
        )
        value = previous[i] + likelihood + prior - proposal
        out[i] = value
        if value > top or math.isnan(value):
            top = value
    if not math.isfinite(top):
        return top
    total = 0.0
    for i in range(count):
        out[i] -= top
        total += math.exp(out[i])
    shift = math.log(total)
    for i in range(count):
        out[i] -= shift
    return top


def log_weights(
    previous: np.ndarray,
    measurement: Measurement,
    residual: np.ndarray,
    prior_deviation: np.ndarray,
    prior_chol: np.ndarray,
    proposal_deviation: np.ndarray,
    proposal_chol: np.ndarray,
) -> np.ndarray | None:
    """The UPF's normalised log-weights by the kernel; None when the kernels are off or the factors are per
    particle (the caller then takes the numpy reference). Every particle lost raises NumericalError."""
    if prior_chol.ndim != 2 or proposal_chol.ndim != 2 or residual.ndim != 2 or not compiled_enabled():
        return None
    outliers = measurement.outlier_probability > 0.0
    mixture = (
        np.array(measurement.mixture_terms(), dtype=float) if outliers else np.zeros((4, residual.shape[1]))
    )
    out = np.empty(len(previous))
    top = log_weights_kernel(
        np.ascontiguousarray(previous, dtype=float),
        np.ascontiguousarray(residual, dtype=float),
        mixture,
        np.ascontiguousarray(measurement.variances, dtype=float),
        outliers,
        np.ascontiguousarray(prior_deviation, dtype=float),
        np.ascontiguousarray(prior_chol, dtype=float),
        np.ascontiguousarray(proposal_deviation, dtype=float),
        np.ascontiguousarray(proposal_chol, dtype=float),
        out,
    )
    if not math.isfinite(top):
        raise NumericalError("every particle has zero weight")
    return out


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernel's one signature; returns the seconds."""
    started = time.perf_counter()
    for outliers in (False, True):
        log_weights_kernel(
            np.zeros(2),
            np.zeros((2, 1)),
            np.zeros((4, 1)),
            np.ones(1),
            outliers,
            np.zeros((2, 1)),
            np.eye(1),
            np.zeros((2, 1)),
            np.eye(1),
            np.empty(2),
        )
    return time.perf_counter() - started
