"""Sigma-point filters equal the linear Kalman filter on linear-Gaussian models.

For a motion model that is linear in the state and a measurement h(x) = H x, the cubature rule and
every unscented point set integrate the first two moments exactly, so the CKF and UKF must reproduce
the textbook Kalman filter (written out here with explicit inverses) to rounding.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.filters import CubatureKalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter
from edgepos.core.filters.base import GaussianFilter
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion import AdaptiveTurn, ConstantAcceleration, ConstantVelocity, CoordinatedTurn, Singer
from edgepos.core.motion.base import MotionModel

TOL = 1e-9


class LinearMeasurement(MeasurementModel):
    """z = H x + v on full-state rows, v ~ N(0, R)."""

    def __init__(self, matrix: np.ndarray, noise: np.ndarray) -> None:
        self.matrix = np.asarray(matrix, dtype=float)
        self.noise = np.asarray(noise, dtype=float)

    @property
    def dim(self) -> int:
        return self.matrix.shape[0]

    @property
    def angle_mask(self) -> np.ndarray:
        return np.zeros(self.dim, dtype=bool)

    def predict(self, states: np.ndarray) -> np.ndarray:
        return states @ self.matrix.T

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.matrix, (states.shape[0], *self.matrix.shape)).copy()

    def noise_covariance(self) -> np.ndarray:
        return self.noise


def position_velocity_measurement() -> LinearMeasurement:
    """Position in x and y plus a mixed velocity row, with correlated noise."""
    matrix = np.zeros((3, layout.FULL_DIM))
    matrix[0, layout.XP] = 1.0
    matrix[1, layout.YP] = 1.0
    matrix[2, layout.XV] = 0.3
    matrix[2, layout.YV] = 0.7
    noise = np.array([[0.5, 0.1, 0.0], [0.1, 0.4, 0.05], [0.0, 0.05, 0.2]])
    return LinearMeasurement(matrix, noise)


def kalman_reference(mean, cov, motion: MotionModel, dt, measurement: LinearMeasurement, observed):
    """Textbook KF step on the model's sub-state: predict, then update with explicit inverse."""
    transition = motion.transition_matrix(mean, dt)
    noise = motion.noise_covariance(mean, dt)
    prior_mean = transition @ mean
    prior_cov = transition @ cov @ transition.T + noise
    h = measurement.matrix[:, list(motion.components)]
    innovation_cov = h @ prior_cov @ h.T + measurement.noise
    gain = prior_cov @ h.T @ np.linalg.inv(innovation_cov)
    residual = observed - h @ prior_mean
    post_mean = prior_mean + gain @ residual
    post_cov = prior_cov - gain @ innovation_cov @ gain.T
    nis = float(residual @ np.linalg.solve(innovation_cov, residual))
    _, log_det = np.linalg.slogdet(innovation_cov)
    log_likelihood = -0.5 * (nis + log_det + residual.size * math.log(2.0 * math.pi))
    return prior_mean, prior_cov, post_mean, post_cov, nis, log_likelihood


MODELS = [
    pytest.param(ConstantVelocity(q=2.0), id="cv"),
    pytest.param(ConstantAcceleration(q=3.5), id="ca"),
    pytest.param(Singer(alpha=0.8, sigma=3.0), id="singer"),
    pytest.param(CoordinatedTurn(q=1.5, omega=0.3), id="ct"),
    pytest.param(CoordinatedTurn(q=1.5, omega=-1e-6), id="ct-near-zero-rate"),
]

FILTERS = [
    pytest.param(CubatureKalmanFilter(), id="ckf"),
    pytest.param(UnscentedKalmanFilter(), id="ukf-default"),
    pytest.param(UnscentedKalmanFilter(alpha=0.5, beta=0.0, kappa=0.0), id="ukf-a0.5-b0-k0"),
    pytest.param(UnscentedKalmanFilter(alpha=0.1, beta=2.0, kappa=1.0), id="ukf-a0.1-b2-k1"),
    pytest.param(UnscentedKalmanFilter(alpha=1.0, beta=2.0, kappa=2.0), id="ukf-a1-b2-k2"),
    pytest.param(ExtendedKalmanFilter(), id="ekf"),
]


def initial_gaussian(motion: MotionModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    dim = motion.dim
    mean = rng.normal(0.0, 5.0, dim)
    root = rng.normal(0.0, 1.0, (dim, dim))
    return mean, root @ root.T + 0.5 * np.eye(dim)


@pytest.mark.parametrize("motion", MODELS)
@pytest.mark.parametrize("filt", FILTERS)
def test_filter_equals_linear_kalman_filter(filt: GaussianFilter, motion: MotionModel) -> None:
    rng = np.random.default_rng(20240601)
    measurement = position_velocity_measurement()
    mean, cov = initial_gaussian(motion, rng)
    ref_mean, ref_cov = mean.copy(), cov.copy()
    for step in range(40):
        dt = (0.05, 0.1, 0.3, 1.0)[step % 4]
        observed = rng.normal(0.0, 10.0, measurement.dim)
        prior_mean, prior_cov, ref_mean, ref_cov, ref_nis, ref_ll = kalman_reference(
            ref_mean, ref_cov, motion, dt, measurement, observed
        )
        mean, cov = filt.predict(mean, cov, motion, dt)
        np.testing.assert_allclose(mean, prior_mean, rtol=TOL, atol=TOL)
        np.testing.assert_allclose(cov, prior_cov, rtol=TOL, atol=TOL)
        mean, cov, nis, log_likelihood = filt.update_one(mean, cov, motion.components, measurement, observed)
        np.testing.assert_allclose(mean, ref_mean, rtol=TOL, atol=TOL)
        np.testing.assert_allclose(cov, ref_cov, rtol=TOL, atol=TOL)
        assert nis == pytest.approx(ref_nis, rel=TOL, abs=TOL)
        assert log_likelihood == pytest.approx(ref_ll, rel=TOL, abs=TOL)


@pytest.mark.parametrize("filt", FILTERS)
def test_bank_update_equals_per_gaussian_kalman_updates(filt: GaussianFilter) -> None:
    """A padded bank of models with different components updates each Gaussian as its own KF."""
    rng = np.random.default_rng(7)
    measurement = position_velocity_measurement()
    observed = np.array([1.0, -2.0, 0.5])
    models = [ConstantVelocity(), ConstantAcceleration(), Singer()]
    from edgepos.core.filters.base import embed_bank

    gaussians = [initial_gaussian(m, rng) for m in models]
    means, covs, active = embed_bank(gaussians, [m.components for m in models])
    result = filt.update(means, covs, active, measurement, observed)
    for b, (motion, (mean, cov)) in enumerate(zip(models, gaussians)):
        idx = list(motion.components)
        h = measurement.matrix[:, idx]
        s = h @ cov @ h.T + measurement.noise
        gain = cov @ h.T @ np.linalg.inv(s)
        np.testing.assert_allclose(
            result.means[b, idx], mean + gain @ (observed - h @ mean), rtol=TOL, atol=TOL
        )
        np.testing.assert_allclose(
            result.covs[b][np.ix_(idx, idx)], cov - gain @ s @ gain.T, rtol=TOL, atol=TOL
        )
        inactive = ~active[b]
        assert np.all(result.means[b, inactive] == 0.0)
        assert np.all(result.covs[b][inactive, :] == 0.0) and np.all(result.covs[b][:, inactive] == 0.0)


@pytest.mark.parametrize(
    "filt",
    [
        pytest.param(CubatureKalmanFilter(), id="ckf"),
        pytest.param(UnscentedKalmanFilter(), id="ukf-default"),
        pytest.param(UnscentedKalmanFilter(alpha=0.5, beta=0.0, kappa=0.0), id="ukf-a0.5-b0-k0"),
    ],
)
@pytest.mark.parametrize("omega", [0.0, 0.35, -1.2])
def test_sigma_point_predict_of_at_with_known_turn_rate_is_linear(filt: GaussianFilter, omega: float) -> None:
    """With the turn rate known (variance ~0, uncorrelated) AT is linear in the other components,
    so the sigma-point prediction equals F P F^T + Q with F the AT transition (eq. 7) at that rate."""
    rng = np.random.default_rng(11)
    motion = AdaptiveTurn(q=3.5, beta=0.02, eta=0.17)
    dt = 0.05
    mean = np.array([10.0, 8.0, 0.4, -3.0, 2.0, -0.1, 2.9, omega])
    root = rng.normal(0.0, 0.5, (7, 7))
    cov = np.zeros((8, 8))
    cov[:7, :7] = root @ root.T + 0.1 * np.eye(7)
    cov[7, 7] = 1e-16
    new_mean, new_cov = filt.predict(mean, cov, motion, dt)
    transition = motion.transition_matrix(mean, dt)
    expected_mean = motion.propagate(mean[None, :], dt)[0]
    expected_cov = transition @ cov @ transition.T + motion.noise_covariance(mean, dt)
    np.testing.assert_allclose(new_mean, expected_mean, rtol=TOL, atol=TOL)
    np.testing.assert_allclose(new_cov, expected_cov, rtol=TOL, atol=TOL)


@pytest.mark.parametrize("filt", FILTERS)
def test_bank_prediction_equals_model_by_model_prediction(filt: GaussianFilter) -> None:
    """predict_bank (linear models batched on padded matrices) agrees with predict per model."""
    from edgepos.core.filters.base import embed_bank
    from edgepos.core.motion import CurrentStatistical

    rng = np.random.default_rng(23)
    models = (
        ConstantVelocity(),
        ConstantAcceleration(),
        Singer(),
        CoordinatedTurn(omega=0.2),
        CurrentStatistical(),
        AdaptiveTurn(),
    )
    gaussians = []
    for model in models:
        mean, cov = initial_gaussian(model, rng)
        if layout.PHI in model.components:
            mean[model.components.index(layout.PHI)] = 3.1
        gaussians.append((mean, cov))
    means, covs, _ = embed_bank(gaussians, [m.components for m in models])
    for dt in (0.05, 0.5):
        new_means, new_covs = filt.predict_bank(means, covs, models, dt)
        for j, (model, (mean, cov)) in enumerate(zip(models, gaussians)):
            idx = list(model.components)
            expected_mean, expected_cov = filt.predict(mean, cov, model, dt)
            np.testing.assert_allclose(new_means[j, idx], expected_mean, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(new_covs[j][np.ix_(idx, idx)], expected_cov, rtol=1e-12, atol=1e-12)
            inactive = [c for c in range(layout.FULL_DIM) if c not in idx]
            assert np.all(new_means[j, inactive] == 0.0)
            assert np.all(new_covs[j][inactive, :] == 0.0) and np.all(new_covs[j][:, inactive] == 0.0)
