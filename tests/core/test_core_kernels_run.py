"""The run's kernel rounds each interval for F and Q as ``motion.base.dt_key`` does (Python's
``round(dt, 9)``), to the bit, or leaves the epoch to the per-epoch path (NaN)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.compiled import compiled_enabled
from edgepos.core.kernels_run import rounded_dt
from edgepos.core.motion.base import dt_key

pytestmark = pytest.mark.skipif(not compiled_enabled(), reason="the run's kernel is compiled only")


def _bits(value: float) -> str:
    return float(value).hex()


def _check(dts: np.ndarray) -> int:
    """Every rounding the kernel gives is dt_key's to the bit; returns how many it left to Python."""
    left = 0
    for dt in dts.tolist():
        rounded = rounded_dt(dt)
        if math.isnan(rounded):
            left += 1
        else:
            assert _bits(rounded) == _bits(dt_key(dt)), dt
    return left


def test_jittered_intervals_round_as_python_rounds() -> None:
    rng = np.random.default_rng(5)
    dts = np.concatenate([0.05 + rng.uniform(-0.004, 0.004, 50_000), 0.05 + rng.normal(0.0, 1e-9, 5_000)])
    assert _check(dts) <= 2  # a near-half is some 4e-8 of them


def test_intervals_over_many_scales_and_signs_round_as_python_rounds() -> None:
    rng = np.random.default_rng(6)
    magnitudes = 10.0 ** rng.uniform(-12.0, 3.0, 50_000)  # to 1000 s (a run's are within max_gap)
    assert _check(magnitudes * rng.choice([-1.0, 1.0], size=magnitudes.size)) <= 20


def test_near_halves_are_rounded_as_python_rounds_or_left_to_it() -> None:
    rng = np.random.default_rng(7)
    whole = rng.integers(1, 10**10, size=20_000).astype(float)
    halves = (whole + 0.5) / 1e9  # the doubles nearest to a half nanosecond
    _check(np.concatenate([halves, np.nextafter(halves, 0.0), np.nextafter(halves, 1.0)]))
    assert math.isnan(rounded_dt(0.0000000025))  # the double nearest 2.5 ns: a near-half


def test_edges() -> None:
    assert _bits(rounded_dt(0.0)) == _bits(0.0) and _bits(rounded_dt(-0.0)) == _bits(0.0)
    assert _bits(rounded_dt(-1e-12)) == _bits(round(-1e-12, 9))  # -0.0, as Python's
    assert math.isnan(rounded_dt(math.nan))
    assert math.isnan(rounded_dt(1e8))  # 1e17 ns: past 2**52, left to Python
    assert _bits(rounded_dt(0.05)) == _bits(0.05)
