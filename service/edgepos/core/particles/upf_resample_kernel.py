"""The UPF's regularised resampling in one compiled loop (numba): ``base.regularised_resample`` with the
Liu-West kernel, for a cloud whose weighted moments the step already has.

The numpy form is some forty calls on (200, 15) arrays, three weighted-moment passes among them, and runs
at about a quarter of the recording's epochs (at an effective sample size below half the particles), where
it took about 0.4 ms. Here it is one loop over the same steps, fed the step's own moments and the random
numbers the numpy form draws, in its order (the systematic draw, then the kernel's normals): the same
particles to rounding (tests/core/test_core_upf_step_kernel.py). The numpy form stays the reference; it runs
with ``EDGEPOS_NUMBA=0``, for the PF, and wherever the kernel declines (the kernel's covariance without a
Cholesky factor: the numpy form repairs or raises), on the generator as it was.

Also the generator every filter draws from: ``epoch_generator(seed, epoch)`` is the generator of
``np.random.default_rng([seed, epoch])`` (the same PCG64 state, so the same draws; tested), its
SeedSequence hashing in a compiled loop (``seed_words_kernel``) and the PCG64 seeding on Python integers,
set on one generator per thread instead of building three objects: about 8 against 2 us, and 20-40 us less
in a pipeline epoch, where numpy's seeding code is no longer in the caches.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.kernels_base import FAILED, OK, _jit, cholesky
from edgepos.core.kernels_base import wrap as _wrap
from edgepos.core.numerics import FloatArray
from edgepos.core.particles.base import kernel_bandwidth
from edgepos.core.particles.upf_step_kernel import weighted_moments_into


@_jit
def _uniform_moments(points: FloatArray, weight: float, angles: np.ndarray, mean: FloatArray) -> FloatArray:
    """``base.weighted_moments`` of ``points`` (N, D) with every weight ``weight``: ``mean`` filled, the
    covariance returned."""
    cov = np.empty((points.shape[1], points.shape[1]))
    weighted_moments_into(points, np.full(points.shape[0], weight), angles, mean, cov)
    return cov


@_jit
def resample_kernel(
    particles: FloatArray,
    log_weights: FloatArray,
    mean: FloatArray,
    cov: FloatArray,
    index: np.ndarray,
    angles: np.ndarray,
    uniform_draw: float,
    normals: FloatArray,
    bandwidth: float,
    out: FloatArray,
) -> int:
    """``base.regularised_resample(particles, log_weights, active, angles, rng)`` into ``out`` (N, D), given
    the weighted ``mean`` and ``cov`` of the cloud and the draws: ``uniform_draw`` (the systematic
    resampling's ``rng.random()``) and ``normals`` (N, k, the kernel's ``rng.standard_normal``). OK, or
    FAILED when the kernel's covariance has no Cholesky factor."""
    count, dim = particles.shape
    k = index.size
    weight = math.exp(-math.log(count))
    squares = 0.0
    cumulative = np.empty(count)
    total = 0.0
    for i in range(count):
        value = math.exp(log_weights[i])
        squares += value * value
        total += value
        cumulative[i] = total
    cumulative[count - 1] = 1.0
    unbiased = 1.0 - squares
    resampled = np.empty((count, dim))
    chosen = 0
    for i in range(count):  # systematic: the first particle whose cumulative weight reaches the position
        position = (uniform_draw + i) / count
        while chosen < count - 1 and cumulative[chosen] < position:
            chosen += 1
        if not cumulative[chosen] >= position:  # past the end (non-finite weights): numpy decides
            return FAILED
        resampled[i, :] = particles[chosen]
    # the Liu-West kernel: centres shrunk towards the mean, then its Gaussian of h^2 times the spread
    centre = np.empty(dim)
    spread = _uniform_moments(resampled, weight, angles, centre)
    shrink = math.sqrt(1.0 - bandwidth * bandwidth)
    block = np.empty((k, k))
    for a in range(k):
        for b in range(k):
            block[a, b] = bandwidth * bandwidth * spread[index[a], index[b]]
    factor = np.empty((k, k))
    if not cholesky(block, k, factor):
        return FAILED
    for i in range(count):
        for a in range(k):
            c = index[a]
            deviation = resampled[i, c] - centre[c]
            if angles[c]:
                deviation = _wrap(deviation)
            value = centre[c] + shrink * deviation
            resampled[i, c] = _wrap(value) if angles[c] else value
    draws = np.dot(normals, factor.T)
    for i in range(count):
        for a in range(k):
            resampled[i, index[a]] += draws[i, a]
        for c in range(dim):
            if angles[c]:
                resampled[i, c] = _wrap(resampled[i, c])
    out[:, :] = resampled
    if count < 2 or unbiased <= 0.0:
        return OK
    # the affine map onto the weighted cloud's mean and unbiased covariance, on the components with spread
    new_mean = np.empty(dim)
    new_cov = _uniform_moments(resampled, weight, angles, new_mean)
    spread_rows = np.empty(k, dtype=np.int64)
    m = 0
    for a in range(k):
        c = index[a]
        if cov[c, c] > 0.0 and new_cov[c, c] > 0.0:
            spread_rows[m] = c
            m += 1
    if m == 0:
        return OK
    source_block = np.empty((m, m))
    target_block = np.empty((m, m))
    for a in range(m):
        for b in range(m):
            source_block[a, b] = new_cov[spread_rows[a], spread_rows[b]]
            target_block[a, b] = cov[spread_rows[a], spread_rows[b]] / unbiased
    source = np.empty((m, m))
    target = np.empty((m, m))
    if not (cholesky(source_block, m, source) and cholesky(target_block, m, target)):
        return OK  # too few distinct particles to map: kept as drawn
    work = np.empty(m)
    for i in range(count):
        for a in range(m):  # source^-1 (x - new mean) by forward substitution
            c = spread_rows[a]
            value = resampled[i, c] - new_mean[c]
            if angles[c]:
                value = _wrap(value)
            for b in range(a):
                value -= source[a, b] * work[b]
            work[a] = value / source[a, a]
        for a in range(m):
            c = spread_rows[a]
            value = 0.0
            for b in range(a + 1):
                value += target[a, b] * work[b]
            out[i, c] = mean[c] + value
        for c in range(dim):
            if angles[c]:
                out[i, c] = _wrap(out[i, c])
    return OK


def compiled_resample(
    particles: np.ndarray,
    log_weights: np.ndarray,
    mean: np.ndarray,
    cov: np.ndarray,
    active: np.ndarray,
    angles: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray | None:
    """``base.regularised_resample`` of a cloud with weighted moments ``mean`` and ``cov`` by the kernel,
    drawing from ``rng`` as the numpy form does; None (``rng`` as it was) when the kernels are off, the
    cloud has fewer than two particles or the kernel declines."""
    count = len(particles)
    if count < 2 or not compiled_enabled():
        return None
    index = np.flatnonzero(active)
    before = rng.bit_generator.state
    uniform_draw = rng.random()
    normals = rng.standard_normal((count, len(index)))
    out = np.empty_like(particles, dtype=float)
    status = resample_kernel(
        np.ascontiguousarray(particles, dtype=float),
        np.ascontiguousarray(log_weights, dtype=float),
        np.array(mean, dtype=float),
        np.array(cov, dtype=float),
        index,
        np.ascontiguousarray(angles, dtype=bool),
        float(uniform_draw),
        normals,
        kernel_bandwidth(count, len(index)),
        out,
    )
    if status == FAILED:
        rng.bit_generator.state = before
        return None
    return out


_INIT_A, _MULT_A, _INIT_B, _MULT_B = 0x43B0D7E5, 0x931E8875, 0x8B51F9DD, 0x58F38DED
_MIX_MULT_L, _MIX_MULT_R, _XSHIFT, _WORD = 0xCA01F9DD, 0x4973F715, 16, 0xFFFFFFFF
"""numpy's SeedSequence constants (numpy/random/bit_generator.pyx: the hash of its pool of four words)."""


@_jit
def seed_words_kernel(entropy: np.ndarray, out: np.ndarray) -> None:
    """``out`` (8,): ``SeedSequence(entropy).generate_state(8, np.uint32)``, the pool of four 32-bit words
    mixed from ``entropy`` (32-bit words, at most four) as numpy's ``mix_entropy`` and ``hashmix`` do. Words
    are held in int64 and masked to 32 bits after every product (a product that wraps keeps its low bits)."""
    pool = np.empty(4, dtype=np.int64)
    hash_const = _INIT_A
    for i in range(4):
        value = entropy[i] if i < entropy.shape[0] else 0
        value ^= hash_const
        hash_const = (hash_const * _MULT_A) & _WORD
        value = (value * hash_const) & _WORD
        pool[i] = value ^ (value >> _XSHIFT)
    for i_src in range(4):
        for i_dst in range(4):
            if i_src != i_dst:
                value = pool[i_src] ^ hash_const
                hash_const = (hash_const * _MULT_A) & _WORD
                value = (value * hash_const) & _WORD
                value ^= value >> _XSHIFT
                mixed = (_MIX_MULT_L * pool[i_dst] - _MIX_MULT_R * value) & _WORD
                pool[i_dst] = mixed ^ (mixed >> _XSHIFT)
    hash_const = _INIT_B
    for i in range(out.shape[0]):
        value = pool[i % 4] ^ hash_const
        hash_const = (hash_const * _MULT_B) & _WORD
        value = (value * hash_const) & _WORD
        out[i] = value ^ (value >> _XSHIFT)


_PCG_MULTIPLIER = (2549297995355413924 << 64) + 4865540595714422341
_MASK_128 = (1 << 128) - 1
_GENERATORS = threading.local()


def _words(value: int) -> list[int]:
    """numpy's ``_int_to_uint32_array``: a non-negative integer's 32-bit words, least significant first."""
    words = [value & _WORD]
    value >>= 32
    while value:
        words.append(value & _WORD)
        value >>= 32
    return words


def epoch_generator(seed: int, epoch: int) -> np.random.Generator:
    """The generator ``np.random.default_rng([seed, epoch])`` makes (the same PCG64 state), on this thread's
    one generator (set, not built: the caller draws from it before its next call on this thread); numpy's
    own when the kernels are off (``EDGEPOS_NUMBA=0``) or the entropy is not two or three 32-bit words."""
    entropy = _words(seed) + _words(epoch)
    if seed < 0 or epoch < 0 or len(entropy) > 4 or not compiled_enabled():
        return np.random.default_rng([seed, epoch])
    words = np.empty(8, dtype=np.int64)
    seed_words_kernel(np.array(entropy, dtype=np.int64), words)
    w = words.tolist()
    # PCG64(seed_seq): four uint64 (little-endian word pairs), the first two the state, the last two the
    # stream; pcg_setseq_128_srandom_r: state 0, inc = 2 stream + 1, a step, state += seed, a step
    initial = (((w[1] << 32) | w[0]) << 64) | (w[3] << 32) | w[2]
    stream = (((w[5] << 32) | w[4]) << 64) | (w[7] << 32) | w[6]
    increment = ((stream << 1) | 1) & _MASK_128
    state = (((increment + initial) & _MASK_128) * _PCG_MULTIPLIER + increment) & _MASK_128
    generator: np.random.Generator | None = getattr(_GENERATORS, "generator", None)
    if generator is None:
        generator = _GENERATORS.generator = np.random.Generator(np.random.PCG64(0))
    generator.bit_generator.state = {
        "bit_generator": "PCG64",
        "state": {"state": state, "inc": increment},
        "has_uint32": 0,
        "uinteger": 0,
    }
    return generator


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernel's one signature; returns the seconds."""
    started = time.perf_counter()
    particles = np.random.default_rng(0).normal(size=(4, 3))
    angles = np.array([False, False, True])
    compiled_resample(
        particles,
        np.full(4, -math.log(4.0)),
        np.zeros(3),
        np.eye(3),
        np.ones(3, dtype=bool),
        angles,
        np.random.default_rng(1),
    )
    seed_words_kernel(np.array([1, 2], dtype=np.int64), np.empty(8, dtype=np.int64))
    return time.perf_counter() - started
