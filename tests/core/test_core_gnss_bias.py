"""The Gauss-Markov GNSS bias block (core/gnss_bias.py) against closed forms and the joint filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import gnss_bias
from edgepos.core.gnss_bias import Bias
from edgepos.core.motion.ca import ConstantAcceleration


@pytest.mark.parametrize("tau, sigma, dt", [(35.0, 2.1, 0.2), (5.0, 1.0, 7.0), (0.1, 3.0, 0.05)])
def test_discretisation_keeps_the_stationary_variance_and_matches_the_closed_form(tau, sigma, dt):
    phi, q = gnss_bias.discretise(tau, sigma, dt)
    assert phi == pytest.approx(math.exp(-dt / tau))
    assert phi * phi * sigma**2 + q == pytest.approx(sigma**2)  # stationary variance preserved
    # Two half steps are one whole step (the process is Markov in continuous time).
    half_phi, half_q = gnss_bias.discretise(tau, sigma, dt / 2)
    assert half_phi * half_phi == pytest.approx(phi)
    assert half_phi * half_phi * half_q + half_q == pytest.approx(q)


def test_discretisation_refuses_nonsense():
    with pytest.raises(ValueError):
        gnss_bias.discretise(0.0, 1.0, 0.2)
    with pytest.raises(ValueError):
        gnss_bias.discretise(1.0, -1.0, 0.2)


def test_a_predicted_bias_stays_at_its_stationary_variance():
    bias = Bias.stationary(2.0)
    transition = ConstantAcceleration(0.3).transition_matrix(np.zeros(6), 0.2)
    for _ in range(50):
        bias = gnss_bias.predict(bias, transition, 10.0, 2.0, 0.2)
    np.testing.assert_allclose(bias.cov, 4.0 * np.eye(2), rtol=1e-12)


def _joint(mean, cov, bias):
    return np.concatenate([mean, bias.mean]), np.block([[cov, bias.cross], [bias.cross.T, bias.cov]])


def test_condition_equals_the_joint_kalman_update_for_a_measurement_of_the_state_alone():
    rng = np.random.default_rng(4)
    a = rng.standard_normal((8, 8))
    joint_cov = a @ a.T + 8 * np.eye(8)
    joint_mean = rng.standard_normal(8)
    mean, cov = joint_mean[:6], joint_cov[:6, :6]
    bias = Bias(joint_mean[6:], joint_cov[6:, 6:], joint_cov[:6, 6:])
    design = rng.standard_normal((3, 6))
    noise = np.diag([0.5, 1.0, 2.0])
    z = rng.standard_normal(3)
    # The full 8-state update with the measurement not touching the bias ...
    full_design = np.hstack([design, np.zeros((3, 2))])
    s = full_design @ joint_cov @ full_design.T + noise
    gain = joint_cov @ full_design.T @ np.linalg.inv(s)
    want_mean = joint_mean + gain @ (z - full_design @ joint_mean)
    want_cov = joint_cov - gain @ s @ gain.T
    # ... against the 6-state update carried over to the bias.
    small_gain = cov @ design.T @ np.linalg.inv(design @ cov @ design.T + noise)
    post_mean = mean + small_gain @ (z - design @ mean)
    post_cov = cov - small_gain @ design @ cov
    got = gnss_bias.condition(bias, mean, cov, post_mean, post_cov)
    got_mean, got_cov = _joint(post_mean, post_cov, got)
    np.testing.assert_allclose(got_mean, want_mean, atol=1e-10)
    np.testing.assert_allclose(got_cov, want_cov, atol=1e-10)


def test_fix_update_is_the_kalman_update_of_position_plus_bias():
    rng = np.random.default_rng(5)
    a = rng.standard_normal((8, 8))
    joint_cov = a @ a.T + 8 * np.eye(8)
    joint_mean = rng.standard_normal(8)
    bias = Bias(joint_mean[6:], joint_cov[6:, 6:], joint_cov[:6, 6:])
    fix = np.array([1.0, -2.0])
    design = np.zeros((2, 8))
    design[0, 0] = design[1, 3] = 1.0
    design[:, 6:] = np.eye(2)
    s = design @ joint_cov @ design.T + 2.0 * np.eye(2)
    gain = joint_cov @ design.T @ np.linalg.inv(s)
    mean, cov, new_bias = gnss_bias.fix_update(joint_mean[:6], joint_cov[:6, :6], bias, fix, 2.0)
    got_mean, got_cov = _joint(mean, cov, new_bias)
    np.testing.assert_allclose(got_mean, joint_mean + gain @ (fix - design @ joint_mean), atol=1e-10)
    np.testing.assert_allclose(got_cov, joint_cov - gain @ s @ gain.T, atol=1e-10)
    assert np.all(np.linalg.eigvalsh(got_cov) > 0)


def test_white_variance_is_the_rest_of_the_reported_variance_with_a_floor():
    assert gnss_bias.white_variance(3.0, 2.0) == pytest.approx(5.0)
    assert gnss_bias.white_variance(2.0, 3.0) == pytest.approx(1.0)  # a quarter of 4


def test_the_block_round_trips_through_one_array():
    bias = Bias(np.array([1.0, 2.0]), np.array([[3.0, 0.5], [0.5, 4.0]]), np.arange(12.0).reshape(6, 2))
    back = Bias.from_arrays(bias.arrays())
    for got, want in ((back.mean, bias.mean), (back.cov, bias.cov), (back.cross, bias.cross)):
        np.testing.assert_array_equal(got, want)


def test_a_filter_with_the_bias_is_consistent_on_correlated_fixes_and_one_without_is_not():
    """A static receiver, fixes every second with a 20 s Gauss-Markov error of 2 m plus 0.5 m white:
    mean NEES of the position over many runs near 2 with the bias states, far above without."""
    tau, sigma, white = 20.0, 2.0, 0.5
    total = math.sqrt(sigma**2 + white**2)
    motion = ConstantAcceleration(0.01)
    rng = np.random.default_rng(9)
    nees_bias, nees_white = [], []
    for _ in range(40):
        error = rng.standard_normal(2) * sigma
        states = {}
        for label in ("bias", "white"):
            cov = np.diag([100.0, 1.0, 0.01] * 2)
            states[label] = (np.zeros(6), cov, Bias.stationary(sigma if label == "bias" else 0.0))
        for k in range(120):
            if k:
                phi, q = gnss_bias.discretise(tau, sigma, 1.0)
                error = phi * error + math.sqrt(q) * rng.standard_normal(2)
            fix = error + rng.standard_normal(2) * white
            for label, (mean, cov, bias) in states.items():
                if k:
                    transition = motion.transition_matrix(mean, 1.0)
                    mean, cov = (
                        transition @ mean,
                        transition @ cov @ transition.T + motion.noise_covariance(mean, 1.0),
                    )
                    bias = gnss_bias.predict(bias, transition, tau, sigma if label == "bias" else 0.0, 1.0)
                r = gnss_bias.white_variance(total, sigma) if label == "bias" else total**2
                mean, cov, bias = gnss_bias.fix_update(mean, cov, bias, fix, r)
                states[label] = (mean, cov, bias)
                if k >= 30:
                    e = mean[[0, 3]]
                    value = float(e @ np.linalg.solve(cov[np.ix_([0, 3], [0, 3])], e))
                    (nees_bias if label == "bias" else nees_white).append(value)
    assert 1.0 <= np.mean(nees_bias) <= 3.0, np.mean(nees_bias)
    assert np.mean(nees_white) > 5.0, np.mean(nees_white)
