"""The consistency scale (core.consistency): innovations whose state part is s^2 times what the filter
claims give s^2 back, whether the measurement noise is small or dominates; NIS over its dof alone would
not; one outlier barely moves it; the memory forgets; the floor at 1; the plain-data round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.consistency import (
    ConsistencyScale,
    gnss_fix_terms,
    innovation_terms,
    scaled_position,
)
from edgepos.core.gnss_bias import Bias

TAU = 20.0


def _feed(
    rng: np.random.Generator,
    true_scale: float,
    state_part: np.ndarray,
    noise: np.ndarray,
    epochs: int,
    dt: float = 0.2,
    memory: ConsistencyScale | None = None,
    start: float = 0.0,
) -> ConsistencyScale:
    """``epochs`` innovations drawn with covariance true_scale * state_part + noise, judged against
    state_part + noise."""
    memory = memory or ConsistencyScale()
    root = np.linalg.cholesky(true_scale * state_part + noise)
    for k in range(epochs):
        nis, share, square = innovation_terms(root @ rng.standard_normal(2), state_part, noise)
        memory = memory.updated(start + dt * k, nis, 2, share, TAU, square=square)
    return memory


@pytest.mark.parametrize("true_scale", [1.0, 2.0, 4.0])
@pytest.mark.parametrize("noise_std", [0.3, 3.5])
def test_innovations_of_a_known_scale_give_it_back(true_scale: float, noise_std: float) -> None:
    # noise_std 3.5 against a state part of about 0.7 m per axis: the papers' scenes' proportions.
    state_part = np.array([[0.5, 0.1], [0.1, 0.4]])
    noise = noise_std**2 * np.eye(2)
    rng = np.random.default_rng(7)
    estimates = [
        _feed(rng, true_scale, state_part, noise, 2000, dt=1.0, memory=None).estimate for _ in range(8)
    ]
    # The estimate's spread per epoch is about sqrt(4) / a; with a = 0.06 (noise 3.5 m) it needs the
    # 2000 epochs of 8 sessions to pin the mean within 15 %.
    assert np.mean(estimates) == pytest.approx(true_scale, rel=0.15 if noise_std > 1.0 else 0.05)


def test_nis_over_its_dof_alone_would_hide_what_the_scale_finds() -> None:
    state_part = np.diag([0.5, 0.4])
    noise = 12.5 * np.eye(2)
    rng = np.random.default_rng(1)
    root = np.linalg.cholesky(4.0 * state_part + noise)
    draws = [innovation_terms(root @ rng.standard_normal(2), state_part, noise) for _ in range(20000)]
    nis = np.array([d[0] for d in draws])
    assert nis.mean() / 2.0 < 1.15  # the plain check barely moves
    memory = ConsistencyScale()
    for k, (e, a, b) in enumerate(draws):
        memory = memory.updated(float(k), e, 2, a, 1e6, square=b)
    assert memory.estimate == pytest.approx(4.0, rel=0.15)


def test_one_outlier_barely_moves_it() -> None:
    state_part = np.diag([2.0, 2.0])
    noise = np.eye(2)
    rng = np.random.default_rng(3)
    memory = _feed(rng, 1.0, state_part, noise, 200)
    before = memory.estimate
    nis, share, square = innovation_terms(np.array([60.0, -40.0]), state_part, noise)  # a 70 m reflection
    assert nis > 1000.0
    after = memory.updated(200 * 0.2, nis, 2, share, TAU, square=square)
    assert after.estimate - before < 0.15
    # without the clip the same epoch would have added (nis - (2 - a)) / sum(a)
    assert (nis - (2.0 - share)) / (memory.share + share) > 10.0


def test_floor_at_one_and_no_history() -> None:
    assert ConsistencyScale().estimate == 1.0 and ConsistencyScale().scale == 1.0
    state_part = np.diag([2.0, 2.0])
    memory = _feed(np.random.default_rng(5), 0.25, state_part, np.eye(2), 400)
    assert memory.estimate < 0.6  # the filter is pessimistic here ...
    assert memory.scale == 1.0  # ... and the scale never claims better than its covariance


def test_memory_follows_a_change_over_its_time_constant() -> None:
    state_part = np.diag([2.0, 2.0])
    rng = np.random.default_rng(11)
    memory = _feed(rng, 1.0, state_part, np.eye(2), 500)
    assert memory.estimate == pytest.approx(1.0, abs=0.3)
    later = _feed(rng, 5.0, state_part, np.eye(2), 5 * int(TAU / 0.2), memory=memory, start=100.0)
    assert later.estimate == pytest.approx(5.0, rel=0.25)


def test_updates_that_say_nothing_leave_it() -> None:
    memory = ConsistencyScale(3.0, 1.5, 2.0)
    assert memory.updated(3.0, math.nan, 2, 0.5, TAU, square=0.2) is memory
    assert memory.updated(3.0, 1.0, 2, 0.0, TAU, square=0.0) is memory
    assert memory.updated(3.0, 1.0, 2, 0.5, TAU, square=math.nan) is memory
    assert innovation_terms(np.zeros(2), np.zeros((2, 2)), -np.eye(2)) == (
        pytest.approx(math.nan, nan_ok=True),
        0.0,
        0.0,
    )


def test_plain_data_round_trip_and_old_states() -> None:
    memory = _feed(np.random.default_rng(2), 2.0, np.diag([1.0, 1.0]), np.eye(2), 30)
    values = memory.to_list()
    assert all(isinstance(v, float) for v in values)
    assert ConsistencyScale.from_list(values) == memory
    assert ConsistencyScale.from_list(None) == ConsistencyScale()  # stored before the scale existed
    assert ConsistencyScale.from_list([]) == ConsistencyScale()
    assert len(values) == 6 and memory.spread_square > 0.0
    # three numbers: written before the bound, the estimate's sums alone
    assert ConsistencyScale.from_list(values[:3]) == ConsistencyScale(*values[:3])
    for bad in ([1.0, 2.0], [1.0, -2.0, 3.0], [math.inf, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0, -1.0, 1.0]):
        with pytest.raises(ValueError):
            ConsistencyScale.from_list(bad)


def test_gnss_fix_terms_count_the_bias_beside_the_state() -> None:
    mean = np.array([10.0, 1.0, 0.0, -5.0, 0.5, 0.0])
    cov = np.diag([1.0, 0.5, 0.1, 2.0, 0.5, 0.1])
    bias = Bias(np.array([0.5, -0.5]), np.diag([4.0, 4.0]), np.zeros((6, 2)))
    bias.cross[0, 0] = bias.cross[3, 1] = -0.5
    fix = np.array([12.0, -6.0])
    nis, share, square = gnss_fix_terms(mean, cov, bias, fix, 1.0)
    state_part = np.diag([1.0 + 4.0 - 1.0, 2.0 + 4.0 - 1.0])
    innovation = fix - mean[[0, 3]] - bias.mean
    total = state_part + np.eye(2)
    assert nis == pytest.approx(float(innovation @ np.linalg.solve(total, innovation)))
    ratio = np.linalg.solve(total, state_part)
    assert share == pytest.approx(float(np.trace(ratio)))
    assert square == pytest.approx(float(np.trace(ratio @ ratio)))


def test_scaled_position_scales_the_block_and_keeps_the_correlations() -> None:
    rng = np.random.default_rng(4)
    root = rng.standard_normal((6, 6))
    cov = root @ root.T
    out = scaled_position(cov, (0, 3), 4.0)
    assert out[np.ix_([0, 3], [0, 3])] == pytest.approx(4.0 * cov[np.ix_([0, 3], [0, 3])])
    assert out[0, 1] == pytest.approx(2.0 * cov[0, 1])
    assert out[1, 2] == cov[1, 2]
    correlation = out / np.sqrt(np.outer(np.diag(out), np.diag(out)))
    assert correlation == pytest.approx(cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov))))
    assert scaled_position(cov, (0, 3), 1.0) is cov


@pytest.mark.parametrize(
    ("true_scale", "noise_std"),
    [
        (3.0, 3.5),
        pytest.param(3.0, 0.3, marks=pytest.mark.slow),
        pytest.param(6.0, 3.5, marks=pytest.mark.slow),
    ],
)
def test_the_upper_bound_covers_the_true_scale_in_its_stated_share(
    true_scale: float, noise_std: float
) -> None:
    # 300 sessions of 300 fixes each (60 s at 5 Hz, 3 memories of 20 s): the papers' proportions (noise 3.5
    # m, a about 0.06) and a sharp case (0.3 m). The bound is below the true scale in about 1 - c of them.
    state_part = np.array([[0.5, 0.1], [0.1, 0.4]])
    noise = noise_std**2 * np.eye(2)
    rng = np.random.default_rng(1)
    memories = [_feed(rng, true_scale, state_part, noise, 300) for _ in range(300)]
    for confidence, (low, high) in ((0.5001, (0.42, 0.58)), (0.9, (0.86, 0.94)), (0.99, (0.975, 1.0))):
        covered = np.mean([m.upper(confidence) >= true_scale for m in memories])
        assert low <= covered <= high, (confidence, covered)
    # the point estimate alone covers about half of them: what the bound is for
    assert 0.35 <= np.mean([m.estimate >= true_scale for m in memories]) <= 0.65


def test_the_upper_bound_grows_with_the_confidence_and_shrinks_with_information() -> None:
    state_part = np.array([[0.5, 0.1], [0.1, 0.4]])
    rng = np.random.default_rng(9)
    short = _feed(rng, 2.0, state_part, 12.25 * np.eye(2), 60)
    long = _feed(rng, 2.0, state_part, 12.25 * np.eye(2), 60, memory=short, start=12.0)
    for memory in (short, long):
        bounds = [memory.upper(c) for c in (0.6, 0.9, 0.99, 0.999, 1.0 - 1e-6)]
        assert all(b >= memory.scale for b in bounds)
        assert bounds == sorted(bounds) and bounds[-1] > bounds[0]
    sharp = _feed(rng, 2.0, state_part, 0.09 * np.eye(2), 60)  # the same fixes count, far more information
    assert sharp.upper(0.99) - sharp.estimate < (short.upper(0.99) - short.estimate) / 5.0
    assert ConsistencyScale().upper(0.99) == math.inf  # no history: nothing bounds it
    one = ConsistencyScale().updated(0.0, 2.0, 2, 0.05, TAU, square=0.0013)
    assert one.upper(0.99) == math.inf  # one fix of the papers' proportions cannot bound it
    with pytest.raises(ValueError):
        short.upper(1.0)
