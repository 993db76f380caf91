"""gnss_tight's compiled range kernel (core/measurements/gnss_kernel.py) against the numpy pseudorange and
range-rate models it replaces in the filters' updates, and the switch back to numpy with EDGEPOS_NUMBA=0."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core.measurements import gnss_kernel
from edgepos.core.measurements.pseudorange import PseudorangeModel
from edgepos.core.measurements.range_rate import RangeRateModel
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GeodeticAnchor

ANCHOR = GeodeticAnchor(np.radians(41.64), np.radians(2.35), 250.0)


def _models(rng: np.random.Generator, rates: bool) -> tuple[PseudorangeModel, RangeRateModel | None]:
    count = 12
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    sats = directions * rng.uniform(2.5e7, 2.8e7, count)[:, None]
    systems = list(rng.choice(["G", "C", "E"], count))
    ranges = PseudorangeModel.build(ANCHOR, sats, systems, rng.normal(0.0, 10.0, count), np.ones(count))
    if not rates:
        return ranges, None
    rate_rows = rng.permutation(count)[:8]  # range rates of a subset, in another order
    model = RangeRateModel.build(
        ANCHOR,
        sats[rate_rows],
        rng.normal(0.0, 2500.0, (8, 3)),
        rng.normal(0.0, 1e-10, 8),
        np.full(8, 0.1),
    )
    return ranges, model


def _states(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    states = np.zeros(shape + (layout.DIM,))
    states[..., :3] = rng.normal(0.0, 300.0, shape + (3,))
    states[..., layout.VE : layout.VU + 1] = rng.normal(0.0, 15.0, shape + (3,))
    states[..., [layout.CLOCK[s] for s in "GCE"]] = rng.normal(0.0, 1e4, shape + (3,))
    states[..., layout.DRIFT] = rng.normal(0.0, 50.0, shape)
    return states


@pytest.mark.parametrize("rates", [True, False])
@pytest.mark.parametrize("shape", [(1,), (200,), (3, 21)])
def test_kernel_predicts_the_numpy_models(rates: bool, shape: tuple[int, ...], monkeypatch) -> None:
    """The same pseudoranges to 1e-6 m (the numpy form's own rounding is 1e-8 m) and range rates to 1e-8
    m/s, over any leading axes (a missing or wrong Sagnac term would be off by metres)."""
    rng = np.random.default_rng(len(shape) * 10 + rates)
    ranges, rate_model = _models(rng, rates)
    states = _states(rng, shape)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    reference = gnss_kernel.epoch_predict(ranges, rate_model)(states)
    monkeypatch.setenv("EDGEPOS_NUMBA", "1")
    compiled = gnss_kernel.epoch_predict(ranges, rate_model)(states)
    m1 = ranges.dim
    assert compiled.shape == reference.shape == shape + (m1 + (rate_model.dim if rate_model else 0),)
    np.testing.assert_allclose(compiled[..., :m1], reference[..., :m1], rtol=0.0, atol=1e-6)
    np.testing.assert_allclose(compiled[..., m1:], reference[..., m1:], rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(reference[..., :m1], ranges.predict(states), rtol=0.0, atol=0.0)
    if rate_model is not None:
        np.testing.assert_allclose(reference[..., m1:], rate_model.predict(states), rtol=0.0, atol=1e-12)


def test_numpy_reference_when_numba_is_off(monkeypatch) -> None:
    """With EDGEPOS_NUMBA=0 the update's h is the models' own numpy code, not the kernel."""
    ranges, _ = _models(np.random.default_rng(1), rates=False)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    assert gnss_kernel.epoch_predict(ranges, None) == ranges.predict
    monkeypatch.setenv("EDGEPOS_NUMBA", "1")
    assert gnss_kernel.epoch_predict(ranges, None) != ranges.predict
    assert gnss_kernel.warm_up() >= 0.0


def test_centre_predictions_match_the_models_and_their_subsets() -> None:
    """``pseudoranges_at`` and ``range_rates_at`` (the pipeline's shared predictions at the centre) give the
    numpy models' values (1e-6 m, 1e-8 m/s), and a subset of the satellites or states exactly the same
    numbers as the whole (each value is computed alone: a test predicting for itself agrees bit for bit)."""
    rng = np.random.default_rng(11)
    ranges, rate_model = _models(rng, True)
    assert rate_model is not None
    states = _states(rng, (4,))
    systems = [next(s for s, i in layout.CLOCK.items() if i == c) for c in ranges.clock_index]
    compiled = gnss_kernel.pseudoranges_at(ANCHOR, states, ranges.sat_position, systems, ranges.known_m)
    assert compiled is not None
    np.testing.assert_allclose(compiled, ranges.predict(states), rtol=0.0, atol=1e-6)
    subset = gnss_kernel.pseudoranges_at(
        ANCHOR, states[2:3], ranges.sat_position[3:7], systems[3:7], ranges.known_m[3:7]
    )
    assert subset is not None
    np.testing.assert_array_equal(subset[0], compiled[2, 3:7])
    drift = -rate_model.known_mps / 299792458.0
    rates = gnss_kernel.range_rates_at(
        ANCHOR, states, rate_model.sat_position, rate_model.sat_velocity, drift
    )
    assert rates is not None
    np.testing.assert_allclose(rates, rate_model.predict(states), rtol=0.0, atol=1e-8)
    alone = gnss_kernel.range_rates_at(
        ANCHOR, states[1:2], rate_model.sat_position[2:3], rate_model.sat_velocity[2:3], drift[2:3]
    )
    assert alone is not None and alone[0, 0] == rates[1, 2]
