"""Covariance intersection (core/intersection.py): consistent whatever the correlation, never more
confident than the independent fusion, and the plain estimate when the other is absent."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core.intersection import WEIGHTS, intersect, range_weight


def _random_spd(rng, n, scale=1.0):
    a = rng.standard_normal((n, n))
    return scale * (a @ a.T + n * np.eye(n))


def _psd(matrix, tol=1e-9):
    return float(np.linalg.eigvalsh(0.5 * (matrix + matrix.T)).min()) >= -tol * max(
        1.0, float(np.abs(matrix).max())
    )


def test_without_the_other_estimate_it_is_the_estimate_itself():
    rng = np.random.default_rng(1)
    mean, cov = rng.standard_normal(3), _random_spd(rng, 3)
    got_mean, got_cov, weight = intersect(mean, cov, None, None)
    np.testing.assert_array_equal(got_mean, mean)
    np.testing.assert_array_equal(got_cov, cov)
    assert weight == 1.0


@pytest.mark.parametrize("seed", range(5))
def test_the_result_bounds_the_true_error_for_any_correlation_and_is_no_tighter_than_independent_fusion(seed):
    rng = np.random.default_rng(seed)
    pa, pb = _random_spd(rng, 2), _random_spd(rng, 2, 3.0)
    mean, cov, weight = intersect(np.zeros(2), pa, np.ones(2), pb)
    info_a, info_b = np.linalg.inv(pa), np.linalg.inv(pb)
    gain_a, gain_b = cov @ (weight * info_a), cov @ ((1.0 - weight) * info_b)
    np.testing.assert_allclose(mean, gain_b @ np.ones(2), atol=1e-12)  # x = P (w Pa^-1 xa + (1-w) Pb^-1 xb)
    independent = np.linalg.inv(info_a + info_b)
    assert _psd(cov - independent)  # never claims more than the Kalman (independent) fusion
    assert float(np.trace(cov)) <= min(np.trace(pa), np.trace(pb)) + 1e-9  # the trace is minimised over w
    for correlation in (-0.9, 0.0, 0.5, 0.99):
        # Errors with marginals pa, pb and a cross-covariance of the given strength.
        la, lb = np.linalg.cholesky(pa), np.linalg.cholesky(pb)
        cross = correlation * la @ lb.T
        joint = np.block([[pa, cross], [cross.T, pb]])
        gains = np.hstack([gain_a, gain_b])
        actual = gains @ joint @ gains.T
        assert _psd(cov - actual), correlation  # consistent: the claimed covariance bounds the actual


@pytest.mark.parametrize("seed", range(5))
def test_the_block_diagonal_bound_of_range_weight_holds_for_correlated_neighbours(seed):
    """blockdiag(P0 / w, Pj * m / (1 - w)) >= the joint covariance for any cross-correlation."""
    rng = np.random.default_rng(10 + seed)
    blocks = [_random_spd(rng, 2) for _ in range(4)]
    factors = [np.linalg.cholesky(b) for b in blocks]
    shared = rng.standard_normal((2, 2))  # a common error component through every block
    joint = np.zeros((8, 8))
    for i in range(4):
        for j in range(4):
            joint[2 * i : 2 * i + 2, 2 * j : 2 * j + 2] = (
                blocks[i] if i == j else 0.9 * factors[i] @ shared @ np.linalg.pinv(shared) @ factors[j].T
            )
    joint = 0.5 * (joint + joint.T)
    if np.linalg.eigvalsh(joint).min() < 0:
        joint += (1e-9 - np.linalg.eigvalsh(joint).min()) * np.eye(8)
    for w in WEIGHTS[:-1]:
        bound = np.zeros((8, 8))
        bound[:2, :2] = blocks[0] / w
        for k in range(1, 4):
            bound[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = blocks[k] * 3 / (1.0 - w)
        assert _psd(bound - joint + 1e-9 * np.eye(8))


def test_range_weight_uses_informative_ranges_and_ignores_useless_ones():
    cov = np.diag([25.0, 1.0, 0.1, 25.0, 1.0, 0.1])
    design = np.zeros((2, 6))
    design[0, 0] = design[1, 3] = 1.0
    neighbour_design = np.zeros((2, 4))
    neighbour_design[0, 0] = neighbour_design[1, 3] = -1.0
    precise = np.eye(4) * 0.01
    weight = range_weight(cov, design, neighbour_design, precise, np.eye(2) * 0.01, 2)
    assert 0.0 < weight < 1.0
    vague = np.eye(4) * 1e4
    assert range_weight(cov, design, neighbour_design, vague, np.eye(2) * 0.01, 2) == 1.0
    assert range_weight(cov, design, neighbour_design, precise, np.eye(2), 0) == 1.0
