"""The noise level's compiled per-epoch fit (core/measurements/gnss_noise_kernel.py) against the numpy form
of gnss/noise_level.py ``epoch_scale`` it replaces, and the kernel declining to the numpy form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import compiled
from edgepos.core.measurements import gnss_noise_kernel
from edgepos.gnss.noise_level import epoch_scale

pytestmark = pytest.mark.skipif(
    not compiled.compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)"
)


def _epoch(seed: int, rows: int, groups: int, fault: float, lone: bool):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    jacobian = np.zeros((rows, 3 + groups))
    jacobian[:, :3] = rng.normal(size=(rows, 3))
    jacobian[:, :3] /= np.linalg.norm(jacobian[:, :3], axis=1)[:, None]
    for r in range(rows):
        jacobian[r, 3 + r % groups] = 1.0
    if lone:  # the last row alone on its clock: leverage 1, the fit passes through it
        jacobian = np.hstack([jacobian, np.zeros((rows, 1))])
        jacobian[-1, 3:] = 0.0
        jacobian[-1, -1] = 1.0
    variance = rng.uniform(0.5, 9.0, rows)
    residuals = rng.normal(size=rows) * np.sqrt(variance) * 1.7
    residuals[rng.integers(rows)] += fault
    return jacobian, residuals, variance


def _reference(jacobian, residuals, variance, monkeypatch) -> tuple[float, int]:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    try:
        return epoch_scale(jacobian, residuals, variance)
    finally:
        monkeypatch.setenv("EDGEPOS_NUMBA", "1")


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize(
    ("rows", "groups", "fault", "lone"),
    [
        (20, 3, 0.0, False),
        (20, 3, 80.0, False),
        (9, 2, 60.0, False),
        (8, 3, 0.0, False),
        (7, 3, 0.0, False),
        (15, 2, 50.0, True),
        (5, 1, 0.0, False),
    ],
)
def test_kernel_matches_the_numpy_fit(
    seed: int, rows: int, groups: int, fault: float, lone: bool, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    """The same redundancy and estimate to 1e-9 relative: clean epochs, a faulty row snooped out, one
    redundant row too few to snoop, no redundancy at all, and a row the fit passes through."""
    jacobian, residuals, variance = _epoch(seed, rows, groups, fault, lone)
    got = epoch_scale(jacobian, residuals, variance)
    want = _reference(jacobian, residuals, variance, monkeypatch)
    assert got[1] == want[1]
    if math.isnan(want[0]):
        assert math.isnan(got[0])
    else:
        assert got[0] == pytest.approx(want[0], rel=1e-9)


def test_the_faulty_row_is_snooped_by_both() -> None:
    jacobian, residuals, variance = _epoch(3, 20, 3, 200.0, False)
    estimate, redundancy = epoch_scale(jacobian, residuals, variance)
    assert redundancy == 20 - 6 - 1 and 1.0 < estimate < 10.0


def test_the_kernel_declines_and_the_numpy_form_decides(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A normal matrix that is not positive definite (a negative variance, which the pipeline never
    builds): None from the kernel, and the numpy form's answer from ``epoch_scale``."""
    jacobian, residuals, variance = _epoch(1, 12, 2, 0.0, False)
    variance[:6] *= -1.0
    assert gnss_noise_kernel.epoch_medians(jacobian, residuals, variance) is None
    got = epoch_scale(jacobian, residuals, variance)
    want = _reference(jacobian, residuals, variance, monkeypatch)
    assert got[1] == want[1] and (got[0] == want[0] or (math.isnan(got[0]) and math.isnan(want[0])))


def _honesty_inputs(seed: int, rows: int, tau: float):  # type: ignore[no-untyped-def]
    from edgepos.core.motion import riss as layout

    rng = np.random.default_rng(seed)
    options = {
        "error_correlation": "gauss_markov",
        "code_error_tau_s": tau,
        "code_error_correlated_fraction": 0.57,
    }
    lines = rng.normal(size=(3, rows))
    lines /= np.linalg.norm(lines, axis=0)
    ranges = np.vstack([rng.uniform(2e7, 2.6e7, rows), lines])
    systems = [("G", "C", "E")[k % 3] for k in range(rows)]
    std = rng.uniform(0.5, 5.0, rows)
    smoothing = rng.uniform(0.2, 1.0, rows)
    count = np.where(rng.random(rows) < 0.3, 0.0, rng.uniform(1.0, 100.0, rows))
    a = rng.normal(size=(layout.DIM, layout.DIM))
    predicted_cov = a @ a.T + np.eye(layout.DIM)
    return options, np.arange(rows), std, smoothing, count, ranges, systems, predicted_cov


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(
    ("rows", "tau", "dt"), [(20, 58.0, 1.0), (9, 58.0, 0.2), (12, 0.0, 1.0), (7, 58.0, 5.0), (6, 58.0, 1.0)]
)
def test_honesty_matches_the_numpy_form(seed: int, rows: int, tau: float, dt: float, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """pipelines.gnss_correlation.honesty's factor, memory and bound to 1e-9 relative by the compiled
    kernel and by the numpy form: smoothed and raw rows, white errors (tau 0), and no redundancy (6 rows, 6
    unknowns: factor 1, no bound)."""
    from edgepos.pipelines.gnss_correlation import honesty

    inputs = _honesty_inputs(seed, rows, tau)
    got = honesty(*inputs, dt)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    want = honesty(*inputs, dt)
    assert got.factor == pytest.approx(want.factor, rel=1e-9)
    assert got.memory == pytest.approx(want.memory, rel=1e-9)
    assert (got.bound is None) == (want.bound is None)
    if want.bound is not None:
        np.testing.assert_allclose(got.bound, want.bound, rtol=1e-9, atol=1e-12)
    if rows > 6:
        assert want.factor != 1.0 and want.bound is not None  # compared on real numbers, not defaults
