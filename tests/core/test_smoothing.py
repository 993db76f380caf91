"""Smoothers (``core.smoothing``) against closed forms: RTS equals the batch information-form solution
of a linear-Gaussian chain; Kim's IMM smoother reduces to RTS for one model and for identical models,
and follows its equations written out by hand; fixed lag equals fixed interval on the lag's window;
the pair predictions of a bank match the filters' own predictions and their cross covariances."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.errors import NumericalError
from edgepos.core.filters import CubatureKalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter
from edgepos.core.imm import InteractingMultipleModel
from edgepos.core.motion import make_motion_model
from edgepos.core.smoothing import (
    bank_pair_predictions,
    imm_smooth,
    lag_ends,
    predict_with_cross,
    rts_smooth,
)

TOLERANCE = 1e-9


def cv_model(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """F and Q of a 2-D white-acceleration model on [x, vx, y, vy] (Q positive definite)."""
    axis_f = np.array([[1.0, dt], [0.0, 1.0]])
    axis_q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return np.kron(np.eye(2), axis_f), np.kron(np.eye(2), axis_q)


H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
R = np.array([[0.5, 0.1], [0.1, 0.3]])
M0 = np.array([1.0, 2.0, -1.0, 0.5])
P0 = np.diag([4.0, 1.0, 3.0, 2.0])


def chain(steps: int = 25, seed: int = 3, q: float = 0.8):
    """A linear-Gaussian chain with uneven intervals, its measurements and the Kalman filter's
    moments: (F_k, Q_k for the step k -> k+1, ys, filtered, predicted, cross)."""
    rng = np.random.default_rng(seed)
    dts = rng.uniform(0.05, 0.4, steps - 1)
    models = [cv_model(dt, q) for dt in dts]
    x = M0 + np.sqrt(np.diag(P0)) * rng.standard_normal(4)
    ys = []
    for k in range(steps):
        if k:
            transition, noise = models[k - 1]
            x = transition @ x + np.linalg.cholesky(noise) @ rng.standard_normal(4)
        ys.append(H @ x + np.linalg.cholesky(R) @ rng.standard_normal(2))
    filtered_means, filtered_covs, predicted_means, predicted_covs, cross_covs = [], [], [], [], []
    mean, cov = M0, P0
    for k, y in enumerate(ys):
        if k:
            transition, noise = models[k - 1]
            cross_covs.append(cov @ transition.T)
            mean, cov = transition @ mean, transition @ cov @ transition.T + noise
            predicted_means.append(mean)
            predicted_covs.append(cov)
        gain = cov @ H.T @ np.linalg.inv(H @ cov @ H.T + R)
        mean, cov = mean + gain @ (y - H @ mean), (np.eye(4) - gain @ H) @ cov
        filtered_means.append(mean)
        filtered_covs.append(0.5 * (cov + cov.T))
    moments = tuple(
        np.array(a) for a in (filtered_means, filtered_covs, predicted_means, predicted_covs, cross_covs)
    )
    return models, ys, moments


def information_form(models, ys) -> tuple[np.ndarray, np.ndarray]:
    """The whole interval at once: the posterior of [x_0 .. x_N-1] from its block-tridiagonal
    precision; returns every step's mean and marginal covariance."""
    steps, n = len(ys), 4
    precision = np.zeros((steps * n, steps * n))
    vector = np.zeros(steps * n)

    def block(i, j):
        return slice(i * n, (i + 1) * n), slice(j * n, (j + 1) * n)

    precision[block(0, 0)] += np.linalg.inv(P0)
    vector[:n] += np.linalg.inv(P0) @ M0
    for k, (transition, noise) in enumerate(models):
        inverse_q = np.linalg.inv(noise)
        precision[block(k, k)] += transition.T @ inverse_q @ transition
        precision[block(k + 1, k + 1)] += inverse_q
        precision[block(k, k + 1)] -= transition.T @ inverse_q
        precision[block(k + 1, k)] -= inverse_q @ transition
    inverse_r = np.linalg.inv(R)
    for k, y in enumerate(ys):
        precision[block(k, k)] += H.T @ inverse_r @ H
        vector[k * n : (k + 1) * n] += H.T @ inverse_r @ y
    covariance = np.linalg.inv(precision)
    means = (covariance @ vector).reshape(steps, n)
    covs = np.stack([covariance[block(k, k)] for k in range(steps)])
    return means, covs


def test_rts_equals_the_batch_information_form_solution() -> None:
    models, ys, moments = chain()
    means, covs = rts_smooth(*moments)
    batch_means, batch_covs = information_form(models, ys)
    np.testing.assert_allclose(means, batch_means, rtol=0, atol=TOLERANCE)
    np.testing.assert_allclose(covs, batch_covs, rtol=0, atol=TOLERANCE)
    np.testing.assert_array_equal(means[-1], moments[0][-1])  # the last step is the filter's


def test_rts_covariances_are_symmetric_positive_definite_and_below_the_filtered() -> None:
    _, _, moments = chain(steps=60, q=5.0)
    _, covs = rts_smooth(*moments)
    np.testing.assert_array_equal(covs, covs.transpose(0, 2, 1))
    assert np.linalg.eigvalsh(covs).min() > 0.0
    assert np.linalg.eigvalsh(moments[1] - covs).min() > -1e-12  # smoothing never loses information


def test_rts_of_one_step_is_the_filter() -> None:
    _, _, moments = chain(steps=1)
    means, covs = rts_smooth(
        moments[0], moments[1], np.zeros((0, 4)), np.zeros((0, 4, 4)), np.zeros((0, 4, 4))
    )
    np.testing.assert_array_equal(means, moments[0])
    np.testing.assert_array_equal(covs, moments[1])


def test_rts_refuses_an_indefinite_prediction_and_malformed_ends() -> None:
    _, _, moments = chain(steps=5)
    broken = list(moments)
    broken[3] = moments[3].copy()
    broken[3][2] = -np.eye(4)
    with pytest.raises(NumericalError):
        rts_smooth(*broken)
    with pytest.raises(ValueError):
        rts_smooth(*moments, ends=np.array([1, 0, 2, 3, 4]))  # decreasing
    with pytest.raises(ValueError):
        rts_smooth(*moments, ends=np.array([0, 1, 2, 3, 5]))  # beyond the chain


def test_rts_wraps_angle_differences() -> None:
    """A heading near +-pi: the smoother works on wrapped differences, not across the 2 pi seam."""
    filtered_means = np.array([[math.pi - 0.01], [-math.pi + 0.01]])
    filtered_covs = np.full((2, 1, 1), 0.01)
    predicted = np.array([[math.pi - 0.01]])
    means, _ = rts_smooth(
        filtered_means,
        filtered_covs,
        predicted,
        np.array([[[0.02]]]),
        np.array([[[0.01]]]),
        angle_mask=np.array([True]),
    )
    assert abs(means[0, 0]) > math.pi - 0.01  # moved across the seam by 0.01 rad, not by -2 pi


# -- fixed lag -------------------------------------------------------------------------------------
def test_lag_ends() -> None:
    times = np.array([0.0, 0.05, 0.1, 0.15000000000000002, 0.2, 0.5])
    np.testing.assert_array_equal(lag_ends(times, 0.1), [2, 3, 4, 4, 4, 5])
    np.testing.assert_array_equal(lag_ends(times, 0.0), np.arange(6))
    np.testing.assert_array_equal(lag_ends(times, 10.0), np.full(6, 5))


def test_fixed_lag_beyond_the_interval_is_fixed_interval() -> None:
    _, _, moments = chain()
    times = np.arange(25) * 0.2
    interval = rts_smooth(*moments)
    lagged = rts_smooth(*moments, ends=lag_ends(times, 100.0))
    np.testing.assert_array_equal(lagged[0], interval[0])
    np.testing.assert_array_equal(lagged[1], interval[1])


def test_fixed_lag_is_the_fixed_interval_smoother_of_each_window() -> None:
    _, _, moments = chain()
    lag = 4
    ends = np.minimum(np.arange(25) + lag, 24)
    means, covs = rts_smooth(*moments, ends=ends)
    for k in (0, 7, 20, 21, 24):
        end = ends[k] + 1
        window = [
            moments[0][:end],
            moments[1][:end],
            moments[2][: end - 1],
            moments[3][: end - 1],
            moments[4][: end - 1],
        ]
        window_means, window_covs = rts_smooth(*window)
        np.testing.assert_allclose(means[k], window_means[k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(covs[k], window_covs[k], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(
        rts_smooth(*moments, ends=np.arange(25))[0], moments[0]
    )  # lag 0: the filter


# -- IMM -------------------------------------------------------------------------------------------
def bank_inputs(moments, probabilities: np.ndarray):
    """A bank of identical models over one chain: every model's posterior and every pair's
    prediction is the chain's."""
    filtered_means, filtered_covs, predicted_means, predicted_covs, cross_covs = moments
    count = probabilities.shape[1]

    def per_model(array):
        return np.repeat(array[:, None], count, axis=1)

    def per_pair(array):
        return np.repeat(np.repeat(array[:, None, None], count, axis=1), count, axis=2)

    return (
        per_model(filtered_means),
        per_model(filtered_covs),
        probabilities,
        per_pair(predicted_means),
        per_pair(predicted_covs),
        per_pair(cross_covs),
    )


def test_imm_smoother_with_one_model_is_rts() -> None:
    _, _, moments = chain()
    means, covs, probabilities, pm, pc, cc = bank_inputs(moments, np.ones((25, 1)))
    result = imm_smooth(means, covs, probabilities, np.ones((1, 1)), pm, pc, cc)
    rts_means, rts_covs = rts_smooth(*moments)
    np.testing.assert_allclose(result.means[:, 0], rts_means, rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.covs[:, 0], rts_covs, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(result.probabilities, 1.0)


def test_imm_smoother_with_identical_models_is_rts_and_keeps_the_probabilities() -> None:
    """Identical models have equal likelihoods: the filtered probabilities just follow the Markov
    chain, and the smoothed ones must equal them (the data say nothing about the model)."""
    _, _, moments = chain()
    transition = np.array([[0.9, 0.07, 0.03], [0.2, 0.7, 0.1], [0.05, 0.15, 0.8]])
    probabilities = [np.array([0.7, 0.2, 0.1])]
    for _ in range(24):
        probabilities.append(probabilities[-1] @ transition)
    inputs = bank_inputs(moments, np.array(probabilities))
    means, covs, probs, pm, pc, cc = inputs
    rts_means, _ = rts_smooth(*moments)
    for ends in (None, np.minimum(np.arange(25) + 5, 24)):
        result = imm_smooth(means, covs, probs, transition, pm, pc, cc, ends=ends)
        expected_means, expected_covs = rts_smooth(*moments, ends=ends)
        for model in range(3):
            np.testing.assert_allclose(result.means[:, model], expected_means, rtol=0, atol=1e-12)
            np.testing.assert_allclose(result.covs[:, model], expected_covs, rtol=0, atol=1e-12)
        np.testing.assert_allclose(result.probabilities, probs, rtol=0, atol=1e-12)
    assert not np.allclose(rts_means, moments[0])  # the smoother did move the estimates


def test_imm_smoother_step_written_out() -> None:
    """One backward step of two scalar models, Kim's equations by hand."""
    means = np.array([[[1.0], [1.5]], [[2.0], [3.0]]])
    covs = np.array([[[[0.5]], [[0.8]]], [[[0.3]], [[0.6]]]])
    mu = np.array([[0.6, 0.4], [0.3, 0.7]])
    transition = np.array([[0.9, 0.1], [0.2, 0.8]])
    pm = np.array([[[[2.1], [2.4]], [[2.6], [2.9]]]])  # [k=0, i, j]
    pc = np.array([[[[0.9]], [[1.4]]], [[[1.1]], [[1.7]]]])[None]
    cc = np.array([[[[0.45]], [[0.5]]], [[[0.7]], [[0.75]]]])[None]
    result = imm_smooth(means, covs, mu, transition, pm, pc, cc)

    predicted = mu[0] @ transition  # c_1(j)
    joint = np.array(
        [[transition[i, j] * mu[0, i] / predicted[j] * mu[1, j] for j in range(2)] for i in range(2)]
    )
    smoothed_mu = joint.sum(axis=1)
    for i in range(2):
        pairs = []
        for j in range(2):
            gain = cc[0, i, j, 0, 0] / pc[0, i, j, 0, 0]
            pairs.append(
                (
                    means[0, i, 0] + gain * (means[1, j, 0] - pm[0, i, j, 0]),
                    covs[0, i, 0, 0] + gain * gain * (covs[1, j, 0, 0] - pc[0, i, j, 0, 0]),
                )
            )
        weights = joint[i] / smoothed_mu[i]
        mean = sum(w * m for w, (m, _) in zip(weights, pairs))
        var = sum(w * (p + (m - mean) ** 2) for w, (m, p) in zip(weights, pairs))
        assert result.means[0, i, 0] == pytest.approx(mean, abs=1e-14)
        assert result.covs[0, i, 0, 0] == pytest.approx(var, abs=1e-14)
    np.testing.assert_allclose(result.probabilities[0], smoothed_mu, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(result.probabilities[1], mu[1])
    np.testing.assert_array_equal(result.means[1], means[1])


def test_imm_smoother_keeps_a_model_whose_probability_underflowed_finite() -> None:
    means = np.array([[[1.0], [1.5]], [[2.0], [3.0]]])
    covs = np.full((2, 2, 1, 1), 0.5)
    mu = np.array([[1.0, 0.0], [1.0, 0.0]])  # model 1 has exactly no probability
    pm = np.full((1, 2, 2, 1), 2.0)
    pc = np.full((1, 2, 2, 1, 1), 1.0)
    cc = np.full((1, 2, 2, 1, 1), 0.5)
    result = imm_smooth(means, covs, mu, np.eye(2), pm, pc, cc)
    assert np.isfinite(result.means).all() and np.isfinite(result.covs).all()
    np.testing.assert_array_equal(result.probabilities, mu)


# -- the pair predictions of a bank --------------------------------------------------------------------
def paper_bank(filt, transition_diagonal: float = 0.98) -> InteractingMultipleModel:
    models = [make_motion_model(name) for name in ("ca", "at", "singer")]
    transition = np.full((3, 3), (1 - transition_diagonal) / 2)
    np.fill_diagonal(transition, transition_diagonal)
    return InteractingMultipleModel(models, filt, transition, [0, 1])


def posteriors(bank: InteractingMultipleModel, steps: int, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Plausible, different posteriors of every model at ``steps`` epochs (padded)."""
    rng = np.random.default_rng(seed)
    means, covs = [], []
    for _ in range(steps):
        mean = np.array([10.0, 12.0, 0.5, -3.0, 1.0, 0.2, 0.08, 0.05])
        factor = rng.standard_normal((8, 8)) * 0.2
        cov = factor @ factor.T + np.diag([0.3, 0.2, 0.5, 0.3, 0.2, 0.5, 0.01, 0.004])
        bank_means, bank_covs = bank.initial(mean, cov)
        bank_means = bank_means + rng.standard_normal(bank_means.shape) * 0.1 * bank.active
        means.append(bank_means)
        covs.append(bank_covs * (1.0 + 0.3 * rng.uniform(size=(3, 1, 1))))
    return np.array(means), np.array(covs)


@pytest.mark.parametrize("filt", [CubatureKalmanFilter(), UnscentedKalmanFilter(), ExtendedKalmanFilter()])
def test_pair_predictions_of_a_model_with_itself_are_the_filters_prediction(filt) -> None:
    bank = paper_bank(filt)
    means, covs = posteriors(bank, 4)
    dts = np.array([0.05, 0.05, 0.1])
    predicted_means, predicted_covs, cross_covs = bank_pair_predictions(bank, means, covs, dts)
    for k, dt in enumerate(dts):
        own_means, own_covs = filt.predict_bank(means[k], covs[k], bank.models, dt)
        for j in range(3):
            np.testing.assert_allclose(predicted_means[k, j, j], own_means[j], rtol=0, atol=1e-12)
            np.testing.assert_allclose(predicted_covs[k, j, j], own_covs[j], rtol=0, atol=1e-12)
        for j in (0, 2):  # linear models: Cov(x, x') = P F^T, whatever model the state came from
            transition = np.zeros((8, 8))
            idx = np.ix_(layout.KINEMATIC, layout.KINEMATIC)
            transition[idx] = bank.models[j].transition_matrix(np.zeros(6), dt)
            for i in range(3):  # AT's heading and turn rate rows too (by Stein's lemma through x_in)
                np.testing.assert_allclose(cross_covs[k, i, j], covs[k, i] @ transition.T, rtol=0, atol=1e-12)


def test_sigma_point_cross_covariance_written_out() -> None:
    """CKF through the adaptive turn: 2n points m +- sqrt(n) L e_i, weights 1/2n."""
    model = make_motion_model("at")
    rng = np.random.default_rng(1)
    factor = rng.standard_normal((8, 8)) * 0.1
    cov = factor @ factor.T + np.diag([0.3, 0.2, 0.5, 0.3, 0.2, 0.5, 0.01, 0.004])
    mean = np.array([10.0, 12.0, 0.5, -3.0, 1.0, 0.2, 3.1, 0.3])
    predicted, predicted_cov, cross = predict_with_cross(
        CubatureKalmanFilter(), model, mean[None], cov[None], np.array([0.1])
    )
    root = np.linalg.cholesky(cov) * math.sqrt(8)
    points = np.concatenate([mean + root.T, mean - root.T])
    moved = model.propagate(points, 0.1)
    expected_mean, expected_cov = CubatureKalmanFilter().predict(mean, cov, model, 0.1)
    deviations = moved - expected_mean
    deviations[:, layout.PHI] = (deviations[:, layout.PHI] + math.pi) % (2 * math.pi) - math.pi
    expected_cross = (points - mean).T @ deviations / 16
    np.testing.assert_allclose(predicted[0], expected_mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(predicted_cov[0], expected_cov, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cross[0], expected_cross, rtol=0, atol=1e-12)


def test_hand_over_is_the_interaction_with_all_weight_on_one_model() -> None:
    """Model 0 (CA, no heading or turn rate) into model 1 (AT): the mean and covariance at AT's input
    are the bank's interaction with every weight on CA: CA's kinematics, AT's own heading and turn
    rate conditioned on them."""
    filt = CubatureKalmanFilter()
    bank = paper_bank(filt)
    means, covs = posteriors(bank, 2)
    to_at = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])  # everything flows into AT
    mixer = InteractingMultipleModel(bank.models, filt, to_at)
    mixed_means, mixed_covs, _ = mixer.mix(means[0], covs[0], np.array([1.0, 0.0, 0.0]))
    predicted_means, predicted_covs, _ = bank_pair_predictions(bank, means, covs, np.array([0.05]))
    expected_means, expected_covs = filt.predict_bank(mixed_means, mixed_covs, bank.models, 0.05)
    np.testing.assert_allclose(predicted_means[0, 0, 1], expected_means[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(predicted_covs[0, 0, 1], expected_covs[1], rtol=0, atol=1e-12)


def test_imm_smoother_on_a_bank_gives_symmetric_positive_definite_covariances() -> None:
    bank = paper_bank(CubatureKalmanFilter())
    means, covs = posteriors(bank, 30, seed=8)
    rng = np.random.default_rng(2)
    probabilities = rng.dirichlet(np.ones(3), size=30)
    pairs = bank_pair_predictions(bank, means, covs, np.full(29, 0.05))
    for ends in (None, np.minimum(np.arange(30) + 6, 29)):
        result = imm_smooth(
            means, covs, probabilities, bank.transition, *pairs, angle_mask=layout.FULL_ANGLE_MASK, ends=ends
        )
        np.testing.assert_array_equal(result.covs, result.covs.swapaxes(-1, -2))
        for model in range(3):
            active = np.flatnonzero(bank.active[model])
            block = result.covs[:, model][:, active[:, None], active[None, :]]
            assert np.linalg.eigvalsh(block).min() > 0.0
            inactive = ~bank.active[model]
            assert not result.means[:, model, inactive].any() and not result.covs[:, model, inactive].any()
        np.testing.assert_allclose(result.probabilities.sum(axis=1), 1.0, rtol=0, atol=1e-12)
        assert (result.probabilities >= 0.0).all()
