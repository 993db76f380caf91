"""The C/N0-elevation pseudorange noise model: the fit recovers a known model from synthetic residuals, and
the pipeline's fitted values come back from the first half of tests/data/gnss-rover with the documented
command's code."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.gnss.pseudorange_noise import FITTED, NoiseModel, fit, residuals, robust_std

DATA = "tests/data/gnss-rover/"


def test_the_fit_recovers_a_known_model() -> None:
    truth = NoiseModel(0.5, 0.8, 1.5)
    rng = np.random.default_rng(3)
    elevation = np.radians(rng.uniform(10.0, 89.0, 40000))
    cn0 = rng.uniform(22.0, 50.0, 40000)
    values = rng.normal(0.0, truth.std(elevation, cn0))
    for robust in (False, True):
        model = fit(values, elevation, cn0, robust)
        grid_el, grid_cn0 = np.meshgrid(np.radians([12.0, 30.0, 70.0]), [25.0, 35.0, 48.0])
        # the bins' medians stand for a spread of elevations and C/N0, so the recovered std is close, not exact
        assert np.allclose(model.std(grid_el, grid_cn0), truth.std(grid_el, grid_cn0), rtol=0.12)


def test_the_model_grows_at_low_elevation_and_low_cn0() -> None:
    assert FITTED.std(np.radians(15.0), 45.0) > FITTED.std(np.radians(80.0), 45.0)
    assert FITTED.std(np.radians(40.0), 25.0) > 2.0 * FITTED.std(np.radians(40.0), 45.0)
    assert FITTED.std(np.radians(-5.0), 30.0) == pytest.approx(FITTED.std(np.radians(3.0), 30.0))


def test_the_pipelines_values_come_from_the_first_half() -> None:
    values, elevation, cn0 = residuals(
        DATA + "rover-0-5min.rnx", DATA + "broadcast-nav.rnx", DATA + "reference-0-5min.csv", 0, 150
    )
    assert values.size == 2703
    model = fit(values, elevation, cn0)
    for got, expected in ((model.a_m, FITTED.a_m), (model.b_m, FITTED.b_m), (model.c_m, FITTED.c_m)):
        assert got == pytest.approx(expected, abs=0.006)
    assert math.isfinite(model.std(np.radians(30.0), 40.0))


def test_corrected_rows_are_narrower_but_keep_their_tails() -> None:
    """With the reference station's corrections (first half): robust std 1.05 m against 2.07 m, while the
    RMS, the rover's multipath, stays (4.73 against 4.55 m)."""
    files = (DATA + "rover-0-5min.rnx", DATA + "broadcast-nav.rnx", DATA + "reference-0-5min.csv")
    raw = residuals(*files, 0, 150)[0]
    corrected = residuals(*files, 0, 150, base_path=DATA + "base-0-5min.rnx")[0]
    assert 0.8 * raw.size < corrected.size < raw.size
    assert robust_std(corrected) < 0.6 * robust_std(raw)
    assert float(np.sqrt(np.mean(corrected**2))) > 0.9 * float(np.sqrt(np.mean(raw**2)))
