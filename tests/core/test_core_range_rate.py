"""The range-rate model is the time derivative of the pseudorange model along a moving state."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core.measurements.pseudorange import PseudorangeModel
from edgepos.core.measurements.range_rate import RangeRateModel, enu_velocity_to_ecef
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GeodeticAnchor, GnssOnlyModel
from edgepos.gnss.geodesy import geodetic_to_ecef
from edgepos.gnss.orbits import SPEED_OF_LIGHT, sagnac_range, sagnac_range_rate

ANCHOR = GeodeticAnchor(np.radians(41.64), np.radians(2.35), 250.0)
SATELLITES = np.array([[1.5e7, -3.0e6, 2.1e7], [2.2e7, 1.2e7, 8.0e6], [-4.0e6, 1.6e7, 2.0e7]])
SAT_VELOCITY = np.array([[-1200.0, 2500.0, 600.0], [300.0, -1800.0, 2900.0], [2600.0, 400.0, -1500.0]])
SAT_CLOCK = np.array([1.2e-4, -3.0e-5, 4.0e-4])
SAT_DRIFT = np.array([2.0e-11, -5.0e-12, 1.0e-10])


def _state(rng: np.random.Generator) -> np.ndarray:
    state = np.zeros(layout.DIM)
    state[[layout.NORTH, layout.EAST, layout.UP]] = rng.normal(0.0, 500.0, 3)
    state[[layout.VE, layout.VN, layout.VU]] = [14.0, -9.0, 0.4] + rng.normal(0.0, 3.0, 3)
    state[layout.CLOCK["G"]] = 120.0
    state[layout.DRIFT] = 0.8
    return state


def _pseudoranges(state: np.ndarray, t: float) -> np.ndarray:
    """The pseudorange model at time t: the state moved by its own velocity and clock drift, the satellites
    along their velocity, the satellite clocks along their drift."""
    moved = GnssOnlyModel(ANCHOR).propagate(state[None, :].copy(), t)[0]
    known = -SPEED_OF_LIGHT * (SAT_CLOCK + SAT_DRIFT * t)
    model = PseudorangeModel.build(ANCHOR, SATELLITES + SAT_VELOCITY * t, ["G"] * 3, known, np.ones(3))
    return model.predict(moved)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_range_rate_is_the_pseudorange_models_derivative(seed: int) -> None:
    state = _state(np.random.default_rng(seed))
    h = 0.05
    finite = (_pseudoranges(state, h) - _pseudoranges(state, -h)) / (2.0 * h)
    model = RangeRateModel.build(ANCHOR, SATELLITES, SAT_VELOCITY, SAT_DRIFT, np.full(3, 0.1))
    predicted = model.predict(state)
    # The difference's error is h^2 / 6 times the range's third derivative (~1e-4 m/s^3 here) plus rounding
    # (1e-8 m / h): about 1e-7 m/s, measured 5e-8. 1e-5 m/s still catches the Sagnac term's rate (~5e-3 m/s).
    assert predicted == pytest.approx(finite, abs=1e-5)
    # Each term matters at this tolerance: the receiver's velocity, its clock drift, the satellite drift.
    still = state.copy()
    still[[layout.VE, layout.VN, layout.VU]] = 0.0
    assert np.max(np.abs(model.predict(still) - predicted)) > 1.0
    assert model.predict(state) - RangeRateModel.build(
        ANCHOR, SATELLITES, SAT_VELOCITY, np.zeros(3), np.full(3, 0.1)
    ).predict(state) == pytest.approx(-SPEED_OF_LIGHT * SAT_DRIFT)


def test_range_rate_is_vectorised_over_particles() -> None:
    rng = np.random.default_rng(7)
    states = np.stack([_state(rng) for _ in range(5)])[None, :, :].repeat(2, axis=0)  # (2, 5, DIM)
    model = RangeRateModel.build(ANCHOR, SATELLITES, SAT_VELOCITY, SAT_DRIFT, np.full(3, 0.1))
    batch = model.predict(states)
    assert batch.shape == (2, 5, 3)
    for j in range(5):
        assert batch[1, j] == pytest.approx(model.predict(states[1, j]), abs=1e-9)
    assert model.variances() == pytest.approx(np.full(3, 0.01))
    # The model's matrix-product form equals the baseline's direct formula (orbits.sagnac_range_rate).
    lat, lon, height = ANCHOR.geodetic(states)
    receiver = geodetic_to_ecef(lat, lon, height)
    velocity = enu_velocity_to_ecef(lat, lon, states[..., [layout.VE, layout.VN, layout.VU]])
    direct = sagnac_range_rate(SATELLITES, SAT_VELOCITY, receiver[..., None, :], velocity[..., None, :])
    expected = direct + states[..., layout.DRIFT, None] - SPEED_OF_LIGHT * SAT_DRIFT
    assert batch == pytest.approx(expected, abs=1e-6)


def test_pseudorange_models_product_form_is_the_direct_formula() -> None:
    """PseudorangeModel's matrix-product form (|s|^2 - 2 r.s + |r|^2 and the Sagnac term as r . turn)
    equals orbits.sagnac_range to the rounding of 2e7 m ranges, vectorised over leading axes; a wrong
    Sagnac sign or term would be off by metres (omega |s| |r| / c is about 30 m)."""
    rng = np.random.default_rng(9)
    states = np.stack([_state(rng) for _ in range(6)]).reshape(2, 3, layout.DIM)
    known = np.array([3.0, -2.0, 7.5])
    model = PseudorangeModel.build(ANCHOR, SATELLITES, ["G", "G", "G"], known, np.ones(3))
    receiver = ANCHOR.ecef(states)
    direct = sagnac_range(SATELLITES, receiver[..., None, :]) + states[..., layout.CLOCK["G"], None] + known
    batch = model.predict(states)
    assert batch.shape == (2, 3, 3)
    np.testing.assert_allclose(batch, direct, rtol=0.0, atol=1e-6)
    geometric = np.linalg.norm(SATELLITES - receiver[..., None, :], axis=-1)
    assert np.min(np.abs(batch - geometric - states[..., layout.CLOCK["G"], None] - known)) > 1.0
