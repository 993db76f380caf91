"""The augmented unscented update (Qiao & Qu eqs. 8-26) against closed forms: on a linear
measurement it is the Kalman filter on the joint Gaussian; with certain parameters it comes close to
the plain UKF with the parameters as known points (only the spread of the sigma points differs,
sqrt(12) against sqrt(6)); the GNSS fix model's Jacobian against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.augmented import augmented_update
from edgepos.core.filters.ukf import UnscentedKalmanFilter
from edgepos.core.measurements.gnss_fix import GnssPosition
from edgepos.core.measurements.rsu import RsuRange

KIN = layout.KINEMATIC
UKF = UnscentedKalmanFilter(alpha=1.0, beta=2.0, kappa=0.0)


def gaussian(seed: int, dim: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(dim, dim))
    return rng.normal(size=dim) * 5.0, a @ a.T + 0.5 * np.eye(dim)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_linear_measurement_equals_the_kalman_filter_on_the_joint_gaussian(seed):
    mean, cov = gaussian(seed, 6)
    extra_mean, extra_cov = gaussian(seed + 10, 4)  # two neighbours' positions
    # z_j = own position - neighbour j's position (a linear, relative measurement)
    h = np.zeros((4, 10))
    for j in range(2):
        h[2 * j, 0], h[2 * j + 1, 3] = 1.0, 1.0
        h[2 * j, 6 + 2 * j], h[2 * j + 1, 7 + 2 * j] = -1.0, -1.0
    noise = np.diag([1.0, 2.0, 0.5, 1.5])
    observed = np.array([3.0, -2.0, 1.0, 4.0])
    new_mean, new_cov, innovation, innovation_cov = augmented_update(
        UKF, mean, cov, extra_mean, extra_cov, lambda points: points @ h.T, noise, observed
    )
    joint_mean = np.concatenate([mean, extra_mean])
    joint_cov = np.block([[cov, np.zeros((6, 4))], [np.zeros((4, 6)), extra_cov]])
    s = h @ joint_cov @ h.T + noise
    gain = joint_cov @ h.T @ np.linalg.inv(s)
    expected_mean = joint_mean + gain @ (observed - h @ joint_mean)
    expected_cov = joint_cov - gain @ s @ gain.T
    np.testing.assert_allclose(new_mean, expected_mean[:6], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(new_cov, expected_cov[:6, :6], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(innovation_cov, s, rtol=1e-9)
    np.testing.assert_allclose(innovation, observed - h @ joint_mean, atol=1e-9)


def test_certain_neighbours_give_the_plain_ukf_with_known_points():
    mean, cov = gaussian(4, 6)
    points = np.array([[30.0, 5.0], [-20.0, 12.0], [4.0, -25.0]])
    observed = np.array([28.0, 24.0, 26.0])
    count = len(points)

    def ranges(states):
        return np.linalg.norm(
            states[:, 6:].reshape(states.shape[0], count, 2) - states[:, None, [0, 3]], axis=2
        )

    new_mean, new_cov, _, _ = augmented_update(
        UKF, mean, cov, points.reshape(-1), np.eye(2 * count) * 1e-14, ranges, np.eye(count) * 4.0, observed
    )
    plain_mean, plain_cov, _, _ = UKF.update_one(
        mean, cov, KIN, RsuRange(points, np.full(count, 2.0)), observed
    )
    # Not equal: the unscented transform's spread grows with the dimension, and the ranges are
    # nonlinear; the difference is of the order of the range's curvature over the prior spread.
    np.testing.assert_allclose(new_mean, plain_mean, rtol=0, atol=2e-2)
    np.testing.assert_allclose(new_cov, plain_cov, rtol=2e-2, atol=2e-2)
    assert not np.allclose(new_mean, mean, atol=1e-3)  # the update did move the estimate


def test_uncertain_neighbours_make_the_update_more_cautious():
    mean, cov = gaussian(5, 6)
    points = np.array([[30.0, 5.0], [-20.0, 12.0]])

    def ranges(states):
        return np.linalg.norm(states[:, 6:].reshape(states.shape[0], 2, 2) - states[:, None, [0, 3]], axis=2)

    sure = augmented_update(
        UKF, mean, cov, points.reshape(-1), np.eye(4) * 1e-14, ranges, np.eye(2), np.array([30.0, 25.0])
    )
    unsure = augmented_update(
        UKF, mean, cov, points.reshape(-1), np.eye(4) * 9.0, ranges, np.eye(2), np.array([30.0, 25.0])
    )
    assert np.trace(unsure[1]) > np.trace(sure[1])
    assert np.all(np.diag(unsure[3]) > np.diag(sure[3]))


def test_gnss_fix_jacobian_matches_finite_differences():
    model = GnssPosition(3.0)
    state = np.random.default_rng(7).normal(size=(1, layout.FULL_DIM)) * 10.0
    step = 1e-6
    numeric = np.stack(
        [
            (model.predict(state + step * e) - model.predict(state - step * e))[0] / (2 * step)
            for e in np.eye(layout.FULL_DIM)
        ],
        axis=1,
    )
    np.testing.assert_allclose(model.jacobian(state)[0], numeric, atol=1e-8)
    np.testing.assert_allclose(model.noise_covariance(), np.eye(2) * 9.0)
