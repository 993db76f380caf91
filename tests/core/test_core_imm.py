"""IMM and 2IMM (paper eqs. 10-14 and 29-38): reductions to plain filtering and to each other,
the probability bookkeeping, and the interaction and output equations written out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.filters import CubatureKalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter
from edgepos.core.filters.base import GaussianFilter
from edgepos.core.imm import InteractingMultipleModel, StepResult
from edgepos.core.measurements import GyroYawRate, RsuRangeBearing, Stacked
from edgepos.core.motion import make_motion_model
from edgepos.core.updates import JointCorrection

RSUS = np.array([[0.0, -20.0], [60.0, 80.0], [-30.0, 40.0]])
RANGE_STD, BEARING_STD, GYRO_STD = 0.6, math.radians(0.5), math.radians(0.3)
DT = 0.1
SPEED, RATE, RADIUS = 10.0, 0.2, 50.0


def truth(t: float) -> np.ndarray:
    """A constant-rate left turn: the full 8-state at time t."""
    a = RATE * t
    return np.array(
        [
            RADIUS * math.sin(a),
            SPEED * math.cos(a),
            -SPEED * RATE * math.sin(a),
            RADIUS * (1 - math.cos(a)),
            SPEED * math.sin(a),
            SPEED * RATE * math.cos(a),
            (a + math.pi) % (2 * math.pi) - math.pi,
            RATE,
        ]
    )


def measurement_model() -> Stacked:
    return Stacked([RsuRangeBearing(RSUS, RANGE_STD, BEARING_STD), GyroYawRate(GYRO_STD)])


def observations(steps: int, seed: int, extreme_every: int = 0) -> list[np.ndarray]:
    """Noisy measurements of the truth; every ``extreme_every``-th epoch grossly corrupted."""
    rng = np.random.default_rng(seed)
    model = measurement_model()
    noise_std = np.sqrt(np.diag(model.noise_covariance()))
    out = []
    for k in range(1, steps + 1):
        z = model.predict(truth(k * DT)[None, :])[0] + rng.standard_normal(model.dim) * noise_std
        if extreme_every and k % extreme_every == 0:
            z[0] += 800.0  # range 800 m off
            z[3] = z[3] - math.pi  # bearing reversed
            z[-1] = 6.0  # absurd yaw rate
        z[1::2][: len(RSUS)] = (z[1::2][: len(RSUS)] + math.pi) % (2 * math.pi) - math.pi
        out.append(z)
    return out


def initial_gaussian() -> tuple[np.ndarray, np.ndarray]:
    std = np.array([1.0, 1.0, 0.5, 1.0, 1.0, 0.5, 0.1, 0.1])
    rng = np.random.default_rng(99)
    return truth(0.0) + rng.standard_normal(8) * std, np.diag(std**2)


def transition(count: int, stay: float = 0.95) -> np.ndarray:
    if count == 1:
        return np.ones((1, 1))
    matrix = np.full((count, count), (1 - stay) / (count - 1))
    np.fill_diagonal(matrix, stay)
    return matrix


def run_bank(bank: InteractingMultipleModel, zs: list[np.ndarray]) -> list[StepResult]:
    mean, cov = initial_gaussian()
    means, covs = bank.initial(mean, cov)
    probabilities = np.full(len(bank.models), 1.0 / len(bank.models))
    measurement = measurement_model()
    results = []
    for z in zs:
        prediction = bank.predict(means, covs, probabilities, DT)
        result = bank.correct(prediction, JointCorrection(measurement, z))
        means, covs, probabilities = result.means, result.covs, result.probabilities
        results.append(result)
    return results


FILTERS = [
    pytest.param(CubatureKalmanFilter(), id="ckf"),
    pytest.param(UnscentedKalmanFilter(), id="ukf"),
    pytest.param(ExtendedKalmanFilter(), id="ekf"),
]


@pytest.mark.parametrize("filt", FILTERS)
@pytest.mark.parametrize("model_name", ["ca", "at", "singer", "cv", "ct", "current_statistical"])
def test_single_model_imm_is_plain_filtering(filt: GaussianFilter, model_name: str) -> None:
    model = make_motion_model(model_name)
    bank = InteractingMultipleModel([model], filt, np.ones((1, 1)))
    zs = observations(40, seed=1)
    results = run_bank(bank, zs)
    idx = list(model.components)
    mean, cov = initial_gaussian()
    mean, cov = mean[idx], cov[np.ix_(idx, idx)]
    measurement = measurement_model()
    for z, result in zip(zs, results):
        mean, cov = filt.predict(mean, cov, model, DT)
        mean, cov, nis, log_likelihood = filt.update_one(mean, cov, model.components, measurement, z)
        np.testing.assert_allclose(result.means[0, idx], mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(result.covs[0][np.ix_(idx, idx)], cov, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(result.output.mean, mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(result.output.cov, cov, rtol=1e-12, atol=1e-12)
        assert result.output.components == model.components
        assert result.probabilities.tolist() == [1.0]
        assert result.log_likelihoods[0] == pytest.approx(log_likelihood, rel=1e-12, abs=1e-12)
        assert result.nis[0] == pytest.approx(nis, rel=1e-12, abs=1e-12)


def bank_of(
    names: list[str], filt: GaussianFilter, priority=None, stay: float = 0.95
) -> InteractingMultipleModel:
    return InteractingMultipleModel(
        [make_motion_model(n) for n in names], filt, transition(len(names), stay), priority
    )


@pytest.mark.parametrize("filt", FILTERS)
def test_2imm_with_every_model_prioritised_is_imm(filt: GaussianFilter) -> None:
    names = ["ca", "at", "singer"]
    zs = observations(40, seed=2)
    imm = run_bank(bank_of(names, filt), zs)
    two = run_bank(bank_of(names, filt, priority=[0, 1, 2]), zs)
    for a, b in zip(imm, two):
        np.testing.assert_allclose(b.means, a.means, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.covs, a.covs, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.probabilities, a.probabilities, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.output.mean, a.output.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.output.cov, a.output.cov, rtol=1e-12, atol=1e-12)


def test_2imm_with_a_proper_priority_set_differs_from_imm() -> None:
    names = ["ca", "at", "singer"]
    zs = observations(60, seed=3)
    imm = run_bank(bank_of(names, CubatureKalmanFilter()), zs)
    two = run_bank(bank_of(names, CubatureKalmanFilter(), priority=[0, 1]), zs)
    assert bank_of(names, CubatureKalmanFilter(), priority=[0, 1]).is_two_stage
    assert max(np.max(np.abs(a.probabilities - b.probabilities)) for a, b in zip(imm, two)) > 1e-3
    assert max(np.max(np.abs(a.output.mean - b.output.mean)) for a, b in zip(imm, two)) > 1e-6


@pytest.mark.parametrize("filt", FILTERS)
@pytest.mark.parametrize("priority", [None, [0, 1], [1], [0, 2]])
def test_model_probabilities_stay_a_distribution_under_extreme_measurements(
    filt: GaussianFilter, priority
) -> None:
    names = ["ca", "at", "singer"]
    zs = observations(60, seed=4, extreme_every=7)
    for result in run_bank(bank_of(names, filt, priority, stay=0.98), zs):
        assert abs(result.probabilities.sum() - 1.0) <= 1e-12
        assert np.all(result.probabilities >= 0.0) and np.all(result.probabilities <= 1.0)
        assert np.all(np.isfinite(result.output.mean)) and np.all(np.isfinite(result.output.cov))


def test_probabilities_do_not_underflow_when_every_likelihood_is_tiny() -> None:
    """Log-domain bookkeeping: with log-likelihoods around -1e5 every model keeps a defined share."""
    names = ["ca", "at", "singer"]
    bank = bank_of(names, CubatureKalmanFilter(), priority=[0, 1])
    zs = observations(3, seed=5)
    zs[-1] = zs[-1].copy()
    zs[-1][0] += 5000.0
    result = run_bank(bank, zs)[-1]
    assert np.all(result.log_likelihoods < -1e4)
    assert abs(result.probabilities.sum() - 1.0) <= 1e-12
    assert np.all(np.isfinite(result.probabilities))


def _moments(weights, means, covs):
    mean = weights @ means
    cov = sum(w * (c + np.outer(m - mean, m - mean)) for w, m, c in zip(weights, means, covs))
    return mean, cov


@pytest.mark.parametrize("priority", [[0, 1], [1, 2]])
def test_2imm_step_follows_eqs_30_to_38(priority: list[int]) -> None:
    names = ["ca", "at", "singer"]
    bank = bank_of(names, CubatureKalmanFilter(), priority=priority)
    zs = observations(15, seed=6)
    mean, cov = initial_gaussian()
    means, covs = bank.initial(mean, cov)
    probabilities = np.array([0.5, 0.3, 0.2])
    measurement = measurement_model()
    for z in zs:
        prediction = bank.predict(means, covs, probabilities, DT)
        result = bank.correct(prediction, JointCorrection(measurement, z))
        rho = probabilities @ bank.transition  # eq. 11
        np.testing.assert_allclose(prediction.predicted_probabilities, rho, rtol=1e-12)
        likelihood = np.exp(result.log_likelihoods)  # eq. 29
        first = np.array(priority)
        second = np.array([i for i in range(3) if i not in priority])
        mu_first = likelihood[first] * rho[first] / np.sum(likelihood[first] * rho[first])  # eq. 30
        common = list(bank.common)
        cmeans = result.means[:, common]
        ccovs = result.covs[:, common][:, :, common]
        x0, p0 = _moments(mu_first, cmeans[first], ccovs[first])  # eqs. 31-32
        a0 = likelihood[first].max()  # eq. 33
        denominator = np.sum(a0 * rho[first]) + np.sum(likelihood[second] * rho[second])
        mu_second = likelihood[second] * rho[second] / denominator  # eq. 34
        mu0 = np.sum(a0 * rho[first]) / denominator  # eq. 35
        x, p = _moments(
            np.concatenate([[mu0], mu_second]),
            np.vstack([x0, cmeans[second]]),
            np.concatenate([p0[None], ccovs[second]]),
        )  # eqs. 36-37
        expected = np.empty(3)
        expected[first] = mu_first * mu0  # eq. 38
        expected[second] = mu_second
        np.testing.assert_allclose(result.probabilities, expected, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(result.output.mean, x, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(result.output.cov, p, rtol=1e-10, atol=1e-12)
        means, covs, probabilities = result.means, result.covs, result.probabilities


def test_imm_step_follows_eqs_11_to_14_and_its_output_is_the_moment_match() -> None:
    """Models sharing every component (CA, Singer, CT): interaction is plain eqs. 11-14."""
    names = ["ca", "singer", "ct"]
    bank = bank_of(names, CubatureKalmanFilter())
    bank_transition = np.array([[0.9, 0.07, 0.03], [0.1, 0.8, 0.1], [0.2, 0.2, 0.6]])
    bank = InteractingMultipleModel(bank.models, bank.filter, bank_transition)
    rng = np.random.default_rng(8)
    means = np.zeros((3, 8))
    covs = np.zeros((3, 8, 8))
    for j in range(3):
        means[j, :6] = rng.normal(0.0, 3.0, 6)
        root = rng.normal(0.0, 1.0, (6, 6))
        covs[j, :6, :6] = root @ root.T + np.eye(6)
    probabilities = np.array([0.6, 0.3, 0.1])
    mixed_means, mixed_covs, predicted = bank.mix(means, covs, probabilities)
    rho = probabilities @ bank_transition  # eq. 11 (rows of ``transition`` = from-model)
    np.testing.assert_allclose(predicted, rho, rtol=1e-12)
    for j in range(3):
        weights = bank_transition[:, j] * probabilities / rho[j]  # eq. 12
        mean, cov = _moments(weights, means[:, :6], covs[:, :6, :6])  # eqs. 13-14
        np.testing.assert_allclose(mixed_means[j, :6], mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(mixed_covs[j, :6, :6], cov, rtol=1e-12, atol=1e-12)
    output = bank.combine(means, covs, probabilities)
    mean, cov = _moments(probabilities, means[:, :6], covs[:, :6, :6])
    np.testing.assert_allclose(output.mean, mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(output.cov, cov, rtol=1e-12, atol=1e-12)


def test_interaction_with_unequal_dimensions_keeps_own_components_and_pd_covariances() -> None:
    names = ["cv", "ca", "at"]
    rng = np.random.default_rng(9)
    bank = bank_of(names, CubatureKalmanFilter())
    mean = truth(1.0)
    root = rng.normal(0.0, 0.5, (8, 8))
    means, covs = bank.initial(mean, root @ root.T + 0.2 * np.eye(8))
    means = means + rng.normal(0.0, 0.5, means.shape) * bank.active
    assert bank.common == layout.POSITION_VELOCITY
    mixed_means, mixed_covs, _ = bank.mix(means, covs, np.array([0.2, 0.5, 0.3]))
    for j, model in enumerate(bank.models):
        idx = list(model.components)
        block = mixed_covs[j][np.ix_(idx, idx)]
        np.testing.assert_allclose(block, block.T, atol=0.0)
        assert np.linalg.eigvalsh(block).min() > 0.0
        inactive = ~bank.active[j]
        assert np.all(mixed_means[j, inactive] == 0.0) and np.all(mixed_covs[j][inactive] == 0.0)
    # identity transition: nobody mixes with anybody, the bank is returned unchanged
    identity = InteractingMultipleModel(bank.models, bank.filter, np.eye(3))
    same_means, same_covs, _ = identity.mix(means, covs, np.array([0.2, 0.5, 0.3]))
    np.testing.assert_allclose(same_means, means, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(same_covs, covs, rtol=1e-12, atol=1e-12)


def test_bank_configuration_is_checked() -> None:
    from edgepos.core.errors import ConfigurationError

    ca = make_motion_model("ca")
    with pytest.raises(ConfigurationError):
        InteractingMultipleModel([], CubatureKalmanFilter(), np.ones((0, 0)))
    with pytest.raises(ConfigurationError):
        InteractingMultipleModel([ca, ca], CubatureKalmanFilter(), np.ones((3, 3)) / 3)
    with pytest.raises(ConfigurationError):
        InteractingMultipleModel([ca, ca], CubatureKalmanFilter(), np.array([[0.5, 0.6], [0.5, 0.5]]))
    with pytest.raises(ConfigurationError):
        InteractingMultipleModel([ca, ca], CubatureKalmanFilter(), np.array([[1.2, -0.2], [0.5, 0.5]]))
    with pytest.raises(ConfigurationError):
        InteractingMultipleModel([ca, ca, ca], CubatureKalmanFilter(), transition(3), priority=[0, 5])
