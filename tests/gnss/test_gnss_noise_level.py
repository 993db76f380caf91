"""The pseudorange noise level estimate (gnss.noise_level): white noise of a known variance scale s^2 gives
s^2 back once enough epochs are averaged, whatever the geometry's degrees of freedom; one reflected row
barely moves it; the memory's decay, floor and plain-data round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.gnss.noise_level import (
    NoiseLevel,
    epoch_scale,
    expected_median,
    studentised_squares,
)
from scipy import stats


def _geometry(rng: np.random.Generator, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """A Jacobian by north, east, up and two clocks (unit line-of-sight rows) and per-row model variances."""
    sight = rng.standard_normal((rows, 3))
    sight[:, 2] = np.abs(sight[:, 2])
    h = np.zeros((rows, 5))
    h[:, :3] = -sight / np.linalg.norm(sight, axis=1)[:, None]
    h[np.arange(rows) % 2 == 0, 3] = 1.0
    h[np.arange(rows) % 2 == 1, 4] = 1.0
    return h, rng.uniform(0.5, 9.0, rows)


def test_expected_median_matches_the_chi_square_order_statistics() -> None:
    assert expected_median(1) == pytest.approx(1.0, rel=1e-6)
    assert expected_median(401) == pytest.approx(stats.chi2.median(1), rel=0.01)
    rng = np.random.default_rng(3)
    for count in (4, 9, 16):
        simulated = np.median(rng.chisquare(1, (40000, count)), axis=1).mean()
        assert expected_median(count) == pytest.approx(simulated, rel=0.02)


@pytest.mark.parametrize("scale", [0.5, 1.0, 3.0])
@pytest.mark.parametrize("rows", [7, 18])
def test_white_noise_of_known_scale_gives_its_square(scale: float, rows: int) -> None:
    """Noise std scale x sqrt(v_i) on random geometries (rows - 5 degrees of freedom each), 2000 epochs:
    with 18 rows (13 dof, the recording's typical epoch) the redundancy-weighted mean of the epochs' median
    estimates is s^2 within 5 %; with 7 rows (2 dof) the studentised residuals are so dependent that the
    median over-states s^2 (by 1.7x), the safe direction for a covariance."""
    rng = np.random.default_rng(rows)
    level = NoiseLevel()
    for epoch in range(2000):
        h, variance = _geometry(rng, rows)
        truth = rng.standard_normal(5) * 10.0  # the fit absorbs any position and clock offset
        residuals = h @ truth + scale * np.sqrt(variance) * rng.standard_normal(rows)
        estimate, redundancy = epoch_scale(h, residuals, variance)
        assert redundancy in (rows - 5, rows - 6)  # a clean row is rarely snooped out
        level = level.updated(float(epoch), estimate, redundancy, 1.0e9)
    if rows >= 18:
        assert level.estimate == pytest.approx(scale**2, rel=0.05)
    else:
        assert scale**2 < level.estimate < 2.0 * scale**2


def test_studentised_squares_have_unit_mean_under_the_model() -> None:
    """Leverage-corrected: each row's u^2 has expectation 1 (raw post-fit squares would average
    (rows - unknowns) / rows)."""
    rng = np.random.default_rng(5)
    h, variance = _geometry(rng, 8)
    squares = np.array(
        [studentised_squares(h, np.sqrt(variance) * rng.standard_normal(8), variance) for _ in range(20000)]
    )
    np.testing.assert_allclose(squares.mean(axis=0), 1.0, atol=0.05)


def test_one_reflected_row_barely_moves_the_estimate() -> None:
    rng = np.random.default_rng(11)
    clean, biased, mean_square = [], [], []
    for _ in range(400):
        h, variance = _geometry(rng, 16)
        residuals = np.sqrt(variance) * rng.standard_normal(16)
        clean.append(epoch_scale(h, residuals, variance)[0])
        residuals[3] += 30.0 * math.sqrt(variance[3])  # 30 sigma: a reflected signal
        biased.append(epoch_scale(h, residuals, variance)[0])
        mean_square.append(float(np.mean(studentised_squares(h, residuals, variance))))
    assert 0.95 < np.mean(clean) < 1.15  # 11 dof of 16 rows: the median's small upward bias
    assert np.mean(biased) < 1.4 * np.mean(clean)
    assert np.mean(mean_square) > 30.0  # what a mean of squares would have said


def test_too_few_rows_give_no_estimate() -> None:
    rng = np.random.default_rng(1)
    h, variance = _geometry(rng, 5)
    estimate, redundancy = epoch_scale(h, rng.standard_normal(5), variance)
    assert redundancy == 0 and math.isnan(estimate)
    assert NoiseLevel().updated(1.0, estimate, redundancy, 60.0) == NoiseLevel()


def test_the_memory_decays_with_its_time_constant_and_is_floored_at_one() -> None:
    level = NoiseLevel().updated(0.0, 4.0, 10, 60.0)
    assert level.estimate == 4.0 and level.scale == 4.0
    later = level.updated(60.0, 1.0, 10, 60.0)
    weight = math.exp(-1.0)
    assert later.estimate == pytest.approx((4.0 * weight + 1.0) / (weight + 1.0))
    assert NoiseLevel().updated(0.0, 0.3, 10, 60.0).scale == 1.0  # never below the model
    assert NoiseLevel().scale == 1.0


def test_plain_data_round_trips_and_bad_data_is_refused() -> None:
    level = NoiseLevel().updated(12.5, 1.7, 13, 60.0).updated(13.5, 0.1 / 3.0, 12, 60.0)
    assert NoiseLevel.from_list(level.to_list()) == level
    assert NoiseLevel.from_list([]) == NoiseLevel() == NoiseLevel.from_list(None)
    assert NoiseLevel().to_list() == []
    for bad in ([1.0, 2.0], [1.0, -1.0, 3.0], [math.nan, 1.0, 2.0]):
        with pytest.raises(ValueError):
            NoiseLevel.from_list(bad)


def test_the_snooped_estimate_is_the_fit_without_the_faulty_row() -> None:
    """The rank-one downdate gives what fitting the other rows again gives."""
    rng = np.random.default_rng(8)
    h, variance = _geometry(rng, 14)
    residuals = np.sqrt(variance) * rng.standard_normal(14)
    residuals[6] += 40.0 * math.sqrt(variance[6])
    estimate, redundancy = epoch_scale(h, residuals, variance)
    keep = np.arange(14) != 6
    again = studentised_squares(h[keep], residuals[keep], variance[keep])
    assert redundancy == 14 - 1 - 5
    assert estimate == pytest.approx(float(np.median(again)) / expected_median(again.size), rel=1e-9)
