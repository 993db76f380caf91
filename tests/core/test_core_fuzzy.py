"""The fuzzy noise adaptation (Jiang & Chen 2018, Table 1, eq. 20): each rule of the table at inputs that
fire it alone, the memberships, and the factor's bounds and monotonicity between the rules."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core.compiled import compiled_enabled
from edgepos.core.fuzzy import RULES, FuzzyNoise

FUZZY = FuzzyNoise()
ELEVATION = {"low": np.deg2rad(5.0), "mid": np.deg2rad(35.0), "high": np.deg2rad(75.0)}
"""An elevation fully inside each set (rad)."""
CN0 = {"small": 25.0, "large": 50.0}
"""A C/N0 fully inside each set (dB-Hz)."""


def test_the_rule_table_is_the_papers() -> None:
    assert RULES == {
        ("large", "high"): "good",
        ("large", "mid"): "normal",
        ("large", "low"): "normal",
        ("small", "high"): "normal",
        ("small", "mid"): "normal",
        ("small", "low"): "bad",
    }


@pytest.mark.parametrize(("cn0_set", "elevation_set"), sorted(RULES))
def test_each_rule_alone_gives_its_class(cn0_set: str, elevation_set: str) -> None:
    expected = {"good": FUZZY.good, "normal": FUZZY.normal, "bad": FUZZY.bad}[RULES[(cn0_set, elevation_set)]]
    factor = FUZZY.factor(np.array([ELEVATION[elevation_set]]), np.array([CN0[cn0_set]]))
    assert factor[0] == pytest.approx(expected)


def test_memberships_are_full_inside_a_set_and_sum_to_one() -> None:
    elevations = np.deg2rad(np.linspace(-5.0, 90.0, 96))
    cn0 = np.linspace(15.0, 55.0, 81)
    elevation_degrees, cn0_degrees = FUZZY.memberships(elevations, np.full_like(elevations, 40.0))
    np.testing.assert_allclose(sum(elevation_degrees.values()), 1.0)
    _, cn0_only = FUZZY.memberships(np.full_like(cn0, 0.5), cn0)
    np.testing.assert_allclose(cn0_only["small"] + cn0_only["large"], 1.0)
    for name, value in ELEVATION.items():
        degrees, _ = FUZZY.memberships(np.array([value]), np.array([40.0]))
        assert degrees[name][0] == pytest.approx(1.0)
    assert cn0_degrees["large"][0] == pytest.approx((40.0 - 30.0) / 15.0)


def test_factor_is_bounded_and_falls_as_elevation_and_cn0_rise() -> None:
    elevation, cn0 = np.meshgrid(np.deg2rad(np.linspace(0.0, 90.0, 91)), np.linspace(20.0, 55.0, 71))
    factor = FUZZY.factor(elevation, cn0)
    assert factor.min() >= FUZZY.good - 1e-12 and factor.max() <= FUZZY.bad + 1e-12
    assert np.all(np.diff(factor, axis=0) <= 1e-12)  # more C/N0, never more noise
    assert np.all(np.diff(factor, axis=1) <= 1e-12)  # higher, never more noise
    # Eq. 20: sigma_i = mu_i R0, so a pseudorange standard deviation scales with the factor.
    assert FUZZY.factor(np.deg2rad(5.0), 25.0) == pytest.approx(4.0 * FUZZY.factor(np.deg2rad(80.0), 50.0))


@pytest.mark.skipif(not compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)")
def test_the_compiled_factor_is_the_numpy_forms_bit_for_bit(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """``factor``'s compiled loop (core/measurements/gnss_noise_kernel.py) against ``numpy_factor``: the same
    bits on random inputs, on inputs at every breakpoint, with other breakpoints and singletons; a value
    that is not finite, or inputs of two dimensions, go to the numpy form (also with the kernels off)."""
    rng = np.random.default_rng(5)
    other = FuzzyNoise(np.deg2rad(10.0), np.deg2rad(30.0), np.deg2rad(70.0), 28.0, 47.0, 1.0, 2.5, 5.0)
    edges = np.array([FUZZY.elevation_low_rad, FUZZY.elevation_mid_rad, FUZZY.elevation_high_rad, -0.1, 1.6])
    for noise in (FUZZY, other):
        for _ in range(200):
            count = int(rng.integers(1, 40))
            elevation = rng.uniform(-0.2, 1.7, count)
            cn0 = rng.uniform(10.0, 60.0, count)
            np.testing.assert_array_equal(noise.factor(elevation, cn0), noise.numpy_factor(elevation, cn0))
        elevation = np.repeat(edges, 5)
        cn0 = np.tile([noise.cn0_small_dbhz, noise.cn0_large_dbhz, 0.0, 37.5, 99.0], 5)
        np.testing.assert_array_equal(noise.factor(elevation, cn0), noise.numpy_factor(elevation, cn0))
    for elevation in (np.array([0.3, np.nan]), np.array([0.3, np.inf])):
        with np.errstate(invalid="ignore"):
            got, want = (
                FUZZY.factor(elevation, np.full(2, 40.0)),
                FUZZY.numpy_factor(elevation, np.full(2, 40.0)),
            )
        np.testing.assert_array_equal(got, want)
    grid = np.full((2, 3), 0.5)
    np.testing.assert_array_equal(
        FUZZY.factor(grid, np.full((2, 3), 40.0)), FUZZY.numpy_factor(grid, np.full((2, 3), 40.0))
    )
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    elevation, cn0 = rng.uniform(0.0, 1.5, 20), rng.uniform(20.0, 50.0, 20)
    np.testing.assert_array_equal(FUZZY.factor(elevation, cn0), FUZZY.numpy_factor(elevation, cn0))
