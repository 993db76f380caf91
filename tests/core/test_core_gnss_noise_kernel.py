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
