"""Numerical safety: robust Cholesky, the shared Kalman correction, covariance health over long runs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.errors import EstimationError, NumericalError
from edgepos.core.filters import (
    CubatureKalmanFilter,
    ExtendedKalmanFilter,
    UnscentedKalmanFilter,
    kalman_correct,
)
from edgepos.core.filters.base import GaussianFilter
from edgepos.core.imm import InteractingMultipleModel
from edgepos.core.measurements import GyroYawRate, RsuRangeBearing, Stacked
from edgepos.core.motion import make_motion_model
from edgepos.core.numerics import robust_cholesky, symmetrize, weighted_mean, wrap_angle
from edgepos.core.updates import JointCorrection


def test_robust_cholesky_of_a_healthy_matrix_is_the_plain_factor() -> None:
    rng = np.random.default_rng(0)
    root = rng.normal(size=(5, 5))
    cov = root @ root.T + np.eye(5)
    np.testing.assert_array_equal(robust_cholesky(cov), np.linalg.cholesky(cov))


@pytest.mark.parametrize("deficiency", [0.0, -1e-14, -1e-12])
def test_robust_cholesky_repairs_a_nearly_singular_psd_matrix(deficiency: float) -> None:
    rng = np.random.default_rng(1)
    vectors = rng.normal(size=(6, 4))
    cov = vectors @ vectors.T  # rank 4: singular
    eigenvalues, eigenvectors = np.linalg.eigh(cov)
    eigenvalues[0] = deficiency * eigenvalues.max()  # a rounding-sized negative eigenvalue
    cov = symmetrize((eigenvectors * eigenvalues) @ eigenvectors.T)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(cov)
    factor = robust_cholesky(cov)
    assert np.all(np.isfinite(factor))
    np.testing.assert_array_equal(factor, np.tril(factor))
    np.testing.assert_allclose(factor @ factor.T, cov, atol=1e-6 * np.abs(cov).max())


def test_robust_cholesky_repairs_a_slightly_asymmetric_matrix() -> None:
    cov = np.array([[4.0, 2.0], [2.0, 1.0]])  # singular
    cov[0, 1] += 1e-15
    factor = robust_cholesky(cov)
    np.testing.assert_allclose(factor @ factor.T, symmetrize(cov), atol=1e-6)


@pytest.mark.parametrize(
    "cov",
    [
        pytest.param(np.array([[1.0, np.nan], [np.nan, 1.0]]), id="nan"),
        pytest.param(np.array([[np.inf, 0.0], [0.0, 1.0]]), id="inf"),
        pytest.param(np.diag([1.0, -0.5]), id="strongly-indefinite"),
        pytest.param(np.array([[1.0, 2.0], [2.0, 1.0]]), id="indefinite-off-diagonal"),
        pytest.param(-np.eye(3), id="negative-definite"),
    ],
)
def test_robust_cholesky_refuses_nan_and_indefinite_input(cov: np.ndarray) -> None:
    with pytest.raises(NumericalError):
        robust_cholesky(cov)


def test_numerical_error_is_an_estimation_error() -> None:
    assert issubclass(NumericalError, EstimationError)


def _correct_inputs(innovation_cov: np.ndarray):
    means = np.zeros((1, 8))
    covs = np.eye(8)[None]
    residuals = np.ones((1, innovation_cov.shape[0]))
    cross = np.zeros((1, 8, innovation_cov.shape[0]))
    cross[0, 0, 0] = 0.5
    return means, covs, residuals, innovation_cov[None], cross


@pytest.mark.parametrize(
    "innovation_cov",
    [
        pytest.param(np.array([[1.0, 0.0], [0.0, -1.0]]), id="indefinite"),
        pytest.param(np.zeros((2, 2)), id="zero"),
        pytest.param(np.array([[1.0, 1.0], [1.0, 1.0]]), id="singular"),
        pytest.param(np.array([[np.nan, 0.0], [0.0, 1.0]]), id="nan"),
    ],
)
def test_kalman_correct_refuses_an_innovation_covariance_that_is_not_pd(innovation_cov: np.ndarray) -> None:
    with pytest.raises(NumericalError):
        kalman_correct(*_correct_inputs(innovation_cov))


def test_kalman_correct_refuses_non_finite_results() -> None:
    means, covs, residuals, innovation_cov, cross = _correct_inputs(np.eye(2))
    residuals[0, 0] = np.inf
    with pytest.raises(NumericalError):
        kalman_correct(means, covs, residuals, innovation_cov, cross)


def test_kalman_correct_matches_the_gain_form() -> None:
    rng = np.random.default_rng(3)
    root = rng.normal(size=(8, 8))
    cov = root @ root.T + np.eye(8)
    h = rng.normal(size=(3, 8))
    s = h @ cov @ h.T + np.diag([0.5, 0.2, 0.1])
    c = cov @ h.T
    r = rng.normal(size=3)
    mean = rng.normal(size=8)
    mean[6] = 0.1  # the heading entry is wrapped; keep it well inside (-pi, pi)
    result = kalman_correct(mean[None], cov[None], r[None], s[None], c[None])
    gain = c @ np.linalg.inv(s)
    np.testing.assert_allclose(result.means[0], mean + gain @ r, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(result.covs[0], cov - gain @ s @ gain.T, rtol=1e-10, atol=1e-10)
    assert result.nis[0] == pytest.approx(r @ np.linalg.solve(s, r), rel=1e-10)
    expected_ll = -0.5 * (r @ np.linalg.solve(s, r) + np.linalg.slogdet(s)[1] + 3 * math.log(2 * math.pi))
    assert result.log_likelihood[0] == pytest.approx(expected_ll, rel=1e-10)


def test_helpers_wrap_and_average_angles() -> None:
    assert wrap_angle(math.pi) == pytest.approx(-math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(-math.pi)
    assert wrap_angle(3 * math.pi + 0.1) == pytest.approx(-math.pi + 0.1)
    points = np.array([[1.0, math.pi - 0.1], [3.0, -math.pi + 0.1]])
    mean = weighted_mean(points, np.array([0.5, 0.5]), np.array([False, True]))
    assert mean[0] == 2.0
    assert abs(abs(mean[1]) - math.pi) < 1e-12


@pytest.mark.parametrize(
    "filt",
    [
        pytest.param(CubatureKalmanFilter(), id="ckf"),
        pytest.param(UnscentedKalmanFilter(), id="ukf"),
        pytest.param(ExtendedKalmanFilter(), id="ekf"),
    ],
)
def test_covariances_stay_symmetric_positive_definite_over_a_long_run(filt: GaussianFilter) -> None:
    """600 epochs of a 2IMM bank with very precise measurements (the hard case for P - K S K^T)."""
    names = ["ca", "at", "singer", "cv"]
    models = [make_motion_model(n) for n in names]
    count = len(models)
    transition = np.full((count, count), 0.02 / (count - 1))
    np.fill_diagonal(transition, 0.98)
    bank = InteractingMultipleModel(models, filt, transition, priority=[0, 1])
    rsus = np.array([[0.0, -4.0], [50.0, 15.0], [-50.0, 15.0]])
    measurement = Stacked([RsuRangeBearing(rsus, 0.01, 1e-4), GyroYawRate(1e-4)])
    rng = np.random.default_rng(12)
    dt = 0.05
    means, covs = bank.initial(
        np.array([0.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]), np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.1, 0.1])
    )
    probabilities = np.full(count, 1.0 / count)
    position, velocity = np.array([0.0, 0.0]), np.array([10.0, 0.0])
    for k in range(600):
        rate = 0.3 * math.sin(0.02 * k)
        rotation = np.array(
            [[math.cos(rate * dt), -math.sin(rate * dt)], [math.sin(rate * dt), math.cos(rate * dt)]]
        )
        velocity = rotation @ velocity
        position = position + velocity * dt
        if abs(position[0]) > 60:  # stay among the RSUs: turn round
            velocity = -velocity
        state = np.zeros((1, 8))
        state[0, [0, 1, 3, 4]] = position[0], velocity[0], position[1], velocity[1]
        state[0, [2, 5]] = -rate * velocity[1], rate * velocity[0]
        z = measurement.predict(state)[0] + rng.standard_normal(measurement.dim) * np.sqrt(
            np.diag(measurement.noise_covariance())
        )
        prediction = bank.predict(means, covs, probabilities, dt)
        result = bank.correct(prediction, JointCorrection(measurement, z))
        means, covs, probabilities = result.means, result.covs, result.probabilities
        for j, model in enumerate(models):
            idx = list(model.components)
            block = covs[j][np.ix_(idx, idx)]
            np.testing.assert_array_equal(block, block.T)
            assert np.linalg.eigvalsh(block).min() > 0.0, f"epoch {k}, model {names[j]}"
        output_cov = result.output.cov
        np.testing.assert_array_equal(output_cov, output_cov.T)
        assert np.linalg.eigvalsh(output_cov).min() > 0.0
