"""The fuzzy noise adaptation (Jiang & Chen 2018, Table 1, eq. 20): each rule of the table at inputs that
fire it alone, the memberships, and the factor's bounds and monotonicity between the rules."""

from __future__ import annotations

import numpy as np
import pytest
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
