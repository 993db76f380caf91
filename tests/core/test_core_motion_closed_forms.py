"""Discretised motion models against their published closed forms.

The closed forms are evaluated in 50-digit decimal arithmetic: several of them (Singer's q11, the
paper's q11 of eq. 9) cancel terms of order one to leave values of order (alpha T)^5, which double
precision cannot evaluate to more than a few digits when alpha T is small.
"""

from __future__ import annotations

import decimal
import math
from collections.abc import Callable

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.errors import ConfigurationError
from edgepos.core.motion import (
    AdaptiveTurn,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    CurrentStatistical,
    Singer,
    make_motion_model,
)

CONTEXT = decimal.Context(prec=50)
D = decimal.Decimal


def exact(func: Callable[..., list[list[decimal.Decimal]]], *args: float) -> np.ndarray:
    """Evaluate a closed form with 50 significant digits; return it as a float matrix."""
    with decimal.localcontext(CONTEXT):
        rows = func(*(D(repr(float(a))) for a in args))
        return np.array([[float(v) for v in row] for row in rows])


def assert_close(actual: np.ndarray, expected: np.ndarray, rtol: float = 1e-11) -> None:
    """Entrywise relative agreement (plus a floor at 1e-14 of the largest entry)."""
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=1e-14 * float(np.max(np.abs(expected))))


# -- the adaptive-turn model (paper eqs. 7-9) -----------------------------------------------------
def paper_f_omega(beta, t):
    e = (-beta * t).exp()
    return [[D(1), (1 - e) / beta], [D(0), e]]


def paper_q_omega(beta, eta, t):
    """Eq. 9: Q_omega = 2 beta eta^2 [q_ij]."""
    e1, e2 = (-beta * t).exp(), (-2 * beta * t).exp()
    q11 = (2 * beta * t - 3 + 4 * e1 - e2) / (2 * beta**3)
    q12 = (1 - 2 * e1 + e2) / (2 * beta**2)
    q22 = (1 - e2) / (2 * beta)
    gain = 2 * beta * eta * eta
    return [[gain * q11, gain * q12], [gain * q12, gain * q22]]


def turn_noise_form(q: float, t: float, noise: str = "discrete") -> np.ndarray:
    """Q of the turn models as documented in core.motion.turn. Discrete: the paper's gain q on
    G = [T^2/2, T, 1] per axis, Q = q^2 G G^T. Continuous: white acceleration of intensity q exactly
    discretised for position and velocity (the CV form), plus q T on the tied acceleration."""
    if noise == "discrete":
        gain = np.array([t**2 / 2, t, 1.0])
        axis = q * q * np.outer(gain, gain)
    else:
        axis = q * np.array([[t**3 / 3, t**2 / 2, 0.0], [t**2 / 2, t, 0.0], [0.0, 0.0, t]])
    return np.kron(np.eye(2), axis)


def classic_turn(omega: float, t: float) -> np.ndarray:
    """The classic coordinated-turn transition on [xp, xv, xa, yp, yv, ya] with a = omega x v."""
    s, c = math.sin(omega * t), math.cos(omega * t)
    so, co = (s / omega, (1 - c) / omega) if omega != 0.0 else (t, 0.0)
    return np.array(
        [
            [1, so, 0, 0, -co, 0],
            [0, c, 0, 0, -s, 0],
            [0, -omega * s, 0, 0, -omega * c, 0],
            [0, co, 0, 1, so, 0],
            [0, s, 0, 0, c, 0],
            [0, omega * c, 0, 0, -omega * s, 0],
        ],
        dtype=float,
    )


AT_PARAMS = [
    pytest.param(0.02, 0.17, 0.05, id="paper-beta0.02-T0.05"),
    pytest.param(0.02, 0.17, 1.0, id="beta0.02-T1"),
    pytest.param(0.5, 0.3, 0.1, id="beta0.5-T0.1"),
    pytest.param(2.0, 1.0, 0.05, id="beta2-T0.05"),
    pytest.param(1.0, 0.05, 3.0, id="beta1-T3"),
]


@pytest.mark.parametrize(("beta", "eta", "dt"), AT_PARAMS)
def test_at_turn_rate_block_matches_eqs_7_and_9(beta: float, eta: float, dt: float) -> None:
    model = AdaptiveTurn(q=3.5, beta=beta, eta=eta)
    mean = np.array([1.0, 10.0, 0.0, 2.0, 1.0, 0.0, 0.3, 0.2])
    transition = model.transition_matrix(mean, dt)
    noise = model.noise_covariance(mean, dt)
    assert_close(transition[6:, 6:], exact(paper_f_omega, beta, dt))
    assert_close(noise[6:, 6:], exact(paper_q_omega, beta, eta, dt), rtol=1e-9)
    # eq. 6: the marginal variance step of omega is eta^2 (1 - exp(-2 beta T))
    assert noise[7, 7] == pytest.approx(eta**2 * -math.expm1(-2 * beta * dt), rel=1e-12)
    # eq. 8: block diagonal diag{Q_CT, Q_omega}; Q_CT as the turn models document it
    assert np.all(noise[:6, 6:] == 0.0) and np.all(noise[6:, :6] == 0.0)
    assert_close(noise[:6, :6], turn_noise_form(3.5, dt))
    assert_close(noise[:6, :6], CoordinatedTurn(q=3.5).noise_covariance(mean[:6], dt))
    assert np.linalg.eigvalsh(noise[6:, 6:]).min() > 0.0
    continuous = AdaptiveTurn(q=3.5, beta=beta, eta=eta, noise="continuous").noise_covariance(mean, dt)
    assert_close(continuous[:6, :6], turn_noise_form(3.5, dt, "continuous"))
    assert np.linalg.eigvalsh(continuous).min() > 0.0


@pytest.mark.parametrize(("beta", "eta", "dt"), AT_PARAMS)
@pytest.mark.parametrize("omega", [0.0, 0.4, -2.5])
def test_at_propagation_is_eq_7_at_each_points_own_turn_rate(
    beta: float, eta: float, dt: float, omega: float
) -> None:
    model = AdaptiveTurn(q=3.5, beta=beta, eta=eta)
    rng = np.random.default_rng(17)
    points = rng.normal(0.0, 5.0, (5, 8))
    points[:, layout.PHI] = rng.uniform(-math.pi, math.pi, 5)
    points[:, layout.OMEGA] = omega + rng.normal(0.0, 0.1, 5) * (omega != 0.0)
    moved = model.propagate(points, dt)
    f_omega = exact(paper_f_omega, beta, dt)
    for point, result in zip(points, moved):
        expected = np.zeros(8)
        expected[:6] = classic_turn(point[layout.OMEGA], dt) @ point[:6]
        expected[6:] = f_omega @ point[6:]
        expected[layout.PHI] = (expected[layout.PHI] + math.pi) % (2 * math.pi) - math.pi
        np.testing.assert_allclose(result, expected, rtol=1e-12, atol=1e-12)
    # the Jacobian's kinematic block is F_CT at the mean's own rate, eq. 7's other diagonal block
    mean = points[0]
    transition = model.transition_matrix(mean, dt)
    np.testing.assert_allclose(
        transition[:6, :6], classic_turn(mean[layout.OMEGA], dt), rtol=1e-12, atol=1e-12
    )
    assert np.all(transition[6:, :6] == 0.0) and np.all(transition[:, layout.PHI][:6] == 0.0)


@pytest.mark.parametrize("omega", [0.0, 0.35, -1.0])
def test_ct_transition_is_the_classic_turn(omega: float) -> None:
    for noise in ("discrete", "continuous"):
        model = CoordinatedTurn(q=2.0, omega=omega, noise=noise)
        for dt in (0.05, 0.7):
            np.testing.assert_allclose(
                model.transition_matrix(np.zeros(6), dt), classic_turn(omega, dt), atol=1e-13
            )
            assert_close(model.noise_covariance(np.zeros(6), dt), turn_noise_form(2.0, dt, noise))


# -- textbook linear models ------------------------------------------------------------------------
@pytest.mark.parametrize("gain", [0.5, 3.5])
@pytest.mark.parametrize("dt", [0.001, 0.05, 1.0])
def test_discrete_noise_forms_are_dwna_and_dwpa(gain: float, dt: float) -> None:
    """The default (the paper's "process-noise gain"): Q = gain^2 G G^T with G = [T^2/2, T] for CV
    (piecewise-constant acceleration) and [T^2/2, T, 1] for CA (piecewise-constant acceleration increment)."""
    cv_axis = gain**2 * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    ca_axis = gain**2 * np.array(
        [[dt**4 / 4, dt**3 / 2, dt**2 / 2], [dt**3 / 2, dt**2, dt], [dt**2 / 2, dt, 1.0]]
    )
    assert_close(ConstantVelocity(q=gain).noise_covariance(np.zeros(4), dt), per_axis(cv_axis))
    assert_close(ConstantAcceleration(q=gain).noise_covariance(np.zeros(6), dt), per_axis(ca_axis))
    assert ConstantVelocity().params()["noise"] == ConstantAcceleration().params()["noise"] == "discrete"


def test_unknown_noise_form_is_refused() -> None:
    with pytest.raises(ConfigurationError):
        ConstantVelocity(noise="pink")


def per_axis(block: np.ndarray) -> np.ndarray:
    n = block.shape[0]
    full = np.zeros((2 * n, 2 * n))
    full[:n, :n] = block
    full[n:, n:] = block
    return full


@pytest.mark.parametrize("q", [0.01, 3.5])
@pytest.mark.parametrize("dt", [0.001, 0.05, 1.0, 4.0])
def test_cv_matches_white_noise_acceleration_form(q: float, dt: float) -> None:
    model = ConstantVelocity(q=q, noise="continuous")
    f = np.array([[1.0, dt], [0.0, 1.0]])
    noise = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    assert_close(model.transition_matrix(np.zeros(4), dt), per_axis(f))
    assert_close(model.noise_covariance(np.zeros(4), dt), per_axis(noise))


@pytest.mark.parametrize("q", [0.01, 3.5])
@pytest.mark.parametrize("dt", [0.001, 0.05, 1.0, 4.0])
def test_ca_matches_white_noise_jerk_form(q: float, dt: float) -> None:
    model = ConstantAcceleration(q=q, noise="continuous")
    f = np.array([[1.0, dt, dt**2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    noise = q * np.array(
        [
            [dt**5 / 20, dt**4 / 8, dt**3 / 6],
            [dt**4 / 8, dt**3 / 3, dt**2 / 2],
            [dt**3 / 6, dt**2 / 2, dt],
        ]
    )
    assert_close(model.transition_matrix(np.zeros(6), dt), per_axis(f))
    assert_close(model.noise_covariance(np.zeros(6), dt), per_axis(noise))


def singer_f(alpha, t):
    e = (-alpha * t).exp()
    return [[D(1), t, (alpha * t - 1 + e) / alpha**2], [D(0), D(1), (1 - e) / alpha], [D(0), D(0), e]]


def singer_q(alpha, sigma, t):
    """Singer (1970), as written in Li & Jilkov's survey: Q = 2 alpha sigma^2 [q_ij]."""
    a, e1, e2 = alpha * t, (-alpha * t).exp(), (-2 * alpha * t).exp()
    q11 = (1 - e2 + 2 * a + 2 * a**3 / 3 - 2 * a**2 - 4 * a * e1) / (2 * alpha**5)
    q12 = (e2 + 1 - 2 * e1 + 2 * a * e1 - 2 * a + a**2) / (2 * alpha**4)
    q13 = (1 - e2 - 2 * a * e1) / (2 * alpha**3)
    q22 = (4 * e1 - 3 - e2 + 2 * a) / (2 * alpha**3)
    q23 = (e2 + 1 - 2 * e1) / (2 * alpha**2)
    q33 = (1 - e2) / (2 * alpha)
    gain = 2 * alpha * sigma * sigma
    return [[gain * v for v in row] for row in ((q11, q12, q13), (q12, q22, q23), (q13, q23, q33))]


SINGER_CASES = [
    pytest.param(0.8, 5.0, 0.05, id="alphaT=0.04-paper"),
    pytest.param(0.1, 2.0, 0.01, id="alphaT=0.001-small"),
    pytest.param(0.05, 1.0, 0.001, id="alphaT=5e-5-tiny"),
    pytest.param(0.5, 3.0, 1.0, id="alphaT=0.5-moderate"),
    pytest.param(2.0, 3.0, 1.0, id="alphaT=2-moderate"),
]


@pytest.mark.parametrize(("alpha", "sigma", "dt"), SINGER_CASES)
def test_singer_matches_singer_1970(alpha: float, sigma: float, dt: float) -> None:
    model = Singer(alpha=alpha, sigma=sigma)
    assert_close(model.transition_matrix(np.zeros(6), dt), per_axis(exact(singer_f, alpha, dt)))
    assert_close(
        model.noise_covariance(np.zeros(6), dt), per_axis(exact(singer_q, alpha, sigma, dt)), rtol=1e-8
    )


def test_singer_tends_to_ca_as_alpha_vanishes() -> None:
    """For alpha -> 0 with 2 alpha sigma^2 = q fixed, Singer's Q is the white-jerk Q."""
    q, dt, alpha = 3.5, 0.5, 1e-7
    singer = Singer(alpha=alpha, sigma=math.sqrt(q / (2 * alpha)))
    continuous_ca = ConstantAcceleration(q, noise="continuous")
    assert_close(
        singer.noise_covariance(np.zeros(6), dt), continuous_ca.noise_covariance(np.zeros(6), dt), rtol=1e-6
    )


# -- current statistical ---------------------------------------------------------------------------
@pytest.mark.parametrize("dt", [0.05, 0.8])
@pytest.mark.parametrize(("ax", "ay"), [(0.0, 0.0), (1.5, -3.0), (-4.95, 4.99), (7.0, -12.0)])
def test_current_statistical_f_is_ca_and_q_scales_with_rayleigh_variance(
    dt: float, ax: float, ay: float
) -> None:
    alpha, a_max, sigma_min = 0.8, 5.0, 0.1
    model = CurrentStatistical(alpha=alpha, a_max=a_max, sigma_min=sigma_min)
    mean = np.array([0.0, 10.0, ax, 0.0, -3.0, ay])
    np.testing.assert_allclose(
        model.transition_matrix(mean, dt),
        ConstantAcceleration().transition_matrix(mean, dt),
        rtol=1e-14,
        atol=1e-15,
    )
    noise = model.noise_covariance(mean, dt)
    unit = exact(singer_q, alpha, 1.0, dt)
    for block, a in ((slice(0, 3), ax), (slice(3, 6), ay)):
        variance = (4 - math.pi) / math.pi * max(a_max - abs(a), sigma_min) ** 2
        assert_close(noise[block, block], variance * unit, rtol=1e-8)
    assert np.all(noise[:3, 3:] == 0.0)
    # the mean-input Singer transition collapses to CA: check it from Singer's own F
    singer = exact(singer_f, alpha, dt)
    mean_input = np.array(
        [
            (-dt + alpha * dt**2 / 2 + (1 - math.exp(-alpha * dt)) / alpha) / alpha,
            dt - (1 - math.exp(-alpha * dt)) / alpha,
            1 - math.exp(-alpha * dt),
        ]
    )
    collapsed = singer.copy()
    collapsed[:, 2] += mean_input
    np.testing.assert_allclose(per_axis(collapsed), model.transition_matrix(mean, dt), atol=1e-12)


# -- registry and parameter checks ------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "params"),
    [
        ("cv", {"q": 0.0}),
        ("ca", {"q": -1.0}),
        ("singer", {"alpha": float("nan")}),
        ("at", {"beta": 0.0}),
        ("ct", {"omega": float("inf")}),
        ("current_statistical", {"a_max": -5.0}),
        ("ca", {"bogus": 1.0}),
        ("nonexistent", {}),
    ],
)
def test_bad_model_parameters_are_configuration_errors(name: str, params: dict) -> None:
    from edgepos.core.errors import ConfigurationError

    with pytest.raises(ConfigurationError):
        make_motion_model(name, **params)


def test_models_rebuild_from_their_params() -> None:
    for model in (
        ConstantVelocity(1.0),
        ConstantAcceleration(2.0),
        Singer(0.3, 2.0),
        CoordinatedTurn(1.0, 0.2),
        AdaptiveTurn(2.0, 0.1, 0.2),
        CurrentStatistical(0.5, 4.0, 0.2),
    ):
        rebuilt = make_motion_model(model.name, **model.params())
        dt = 0.1
        mean = np.linspace(1.0, 2.0, model.dim)
        np.testing.assert_array_equal(rebuilt.transition_matrix(mean, dt), model.transition_matrix(mean, dt))
        np.testing.assert_array_equal(rebuilt.noise_covariance(mean, dt), model.noise_covariance(mean, dt))


# -- long intervals: a session may resume after a gap of tens of seconds ------------------------------
@pytest.mark.parametrize("alpha_t", [10.0, 20.0, 40.0])
def test_singer_noise_stays_accurate_over_long_intervals(alpha_t: float) -> None:
    """Default alpha = 0.8 and a 25 s gap give alpha T = 20: Q must still match Singer's closed form
    (the exact discretisation must not cancel e^{+alpha T} growth against itself)."""
    alpha, sigma = 0.8, 5.0
    dt = alpha_t / alpha
    noise = Singer(alpha=alpha, sigma=sigma).noise_covariance(np.zeros(6), dt)
    assert_close(noise, per_axis(exact(singer_q, alpha, sigma, dt)), rtol=1e-6)
    assert np.linalg.eigvalsh(noise).min() > 0.0


@pytest.mark.parametrize("beta_t", [20.0, 40.0])
def test_at_turn_rate_noise_stays_accurate_over_long_intervals(beta_t: float) -> None:
    beta, eta = 2.0, 0.17
    dt = beta_t / beta
    noise = AdaptiveTurn(beta=beta, eta=eta).noise_covariance(np.zeros(8), dt)
    assert_close(noise[6:, 6:], exact(paper_q_omega, beta, eta, dt), rtol=1e-6)
