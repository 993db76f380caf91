"""Analytic Jacobians (used by the EKF and the gate) against central finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.measurements import GyroYawRate, RsuRange, RsuRangeBearing
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion import (
    AdaptiveTurn,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    CurrentStatistical,
    Singer,
)
from edgepos.core.motion.base import MotionModel
from edgepos.core.numerics import wrap_angle


def central_difference(func, x: np.ndarray, angle_rows: np.ndarray, rel_step: float = 1e-6) -> np.ndarray:
    """d func / dx by central differences; output rows flagged in ``angle_rows`` are wrapped."""
    columns = []
    for i in range(x.size):
        step = rel_step * max(1.0, abs(x[i]))
        plus, minus = x.copy(), x.copy()
        plus[i] += step
        minus[i] -= step
        difference = func(plus) - func(minus)
        difference[angle_rows] = wrap_angle(difference[angle_rows])
        columns.append(difference / (2.0 * step))
    return np.column_stack(columns)


def assert_jacobian_matches(analytic: np.ndarray, numeric: np.ndarray) -> None:
    scale = max(1.0, float(np.max(np.abs(numeric))))
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-7 * scale)


AT_STATES = [
    pytest.param([3.0, 12.0, 0.5, -4.0, 1.0, -0.2, 0.1, 0.0], id="omega=0"),
    pytest.param([3.0, 12.0, 0.5, -4.0, 1.0, -0.2, 0.1, 1e-7], id="omega=1e-7"),
    pytest.param([3.0, 12.0, 0.5, -4.0, 1.0, -0.2, 0.1, -2e-3], id="omega-at-small-turn-threshold"),
    pytest.param([3.0, 12.0, 0.5, -4.0, 1.0, -0.2, 0.1, 0.05], id="omega=0.05"),
    pytest.param([-50.0, -7.0, 1.0, 20.0, 9.0, 3.0, 3.1415, 2.0], id="omega=2-phi-near-pi"),
    pytest.param([100.0, 0.5, -3.0, 1.0, -15.0, 2.0, -3.1415, -3.5], id="omega=-3.5-phi-near-minus-pi"),
    pytest.param([0.0, 25.0, 0.0, 0.0, 0.0, 0.0, math.pi - 1e-9, 0.7], id="phi-at-pi"),
]


@pytest.mark.parametrize("state", AT_STATES)
@pytest.mark.parametrize("dt", [0.05, 0.5, 1.0])
def test_at_transition_matrix_is_the_jacobian_of_propagate(state: list[float], dt: float) -> None:
    model = AdaptiveTurn(q=3.5, beta=0.3, eta=0.17)
    x = np.array(state)
    mask = layout.angle_mask(model.components)
    numeric = central_difference(lambda s: model.propagate(s[None, :], dt)[0], x, mask)
    assert_jacobian_matches(model.transition_matrix(x, dt), numeric)


LINEAR_MODELS = [
    pytest.param(ConstantVelocity(q=1.0), id="cv"),
    pytest.param(ConstantAcceleration(q=2.0), id="ca"),
    pytest.param(Singer(alpha=0.5, sigma=2.0), id="singer"),
    pytest.param(CoordinatedTurn(q=1.0, omega=0.4), id="ct"),
    pytest.param(CoordinatedTurn(q=1.0, omega=0.0), id="ct-zero-rate"),
    pytest.param(CurrentStatistical(alpha=0.8, a_max=5.0), id="current_statistical"),
]


@pytest.mark.parametrize("model", LINEAR_MODELS)
@pytest.mark.parametrize("dt", [0.05, 1.0])
def test_linear_model_transition_matrix_is_the_jacobian_of_propagate(model: MotionModel, dt: float) -> None:
    rng = np.random.default_rng(3)
    for _ in range(3):
        x = rng.normal(0.0, 10.0, model.dim)
        mask = layout.angle_mask(model.components)
        numeric = central_difference(lambda s: model.propagate(s[None, :], dt)[0], x, mask)
        assert_jacobian_matches(model.transition_matrix(x, dt), numeric)
        # linear: propagate is exactly F x
        np.testing.assert_allclose(
            model.propagate(x[None, :], dt)[0], model.transition_matrix(x, dt) @ x, atol=1e-12
        )


RSU_POSITIONS = np.array([[0.0, 0.0], [100.0, -3.875], [-40.0, 15.125]])

MEASUREMENT_STATES = [
    pytest.param([30.0, 10.0, 1.0, 4.0, 2.0, 0.5, 0.2, 0.1], id="generic"),
    # due west of the first RSU: its bearing sits on the +-pi cut
    pytest.param([-25.0, -10.0, 0.0, 1e-9, 0.3, 0.0, 3.1, 0.0], id="bearing-on-pi-cut"),
    pytest.param([-25.0, -10.0, 0.0, -1e-9, 0.3, 0.0, 3.1, 0.0], id="bearing-on-minus-pi-cut"),
    pytest.param([99.0, 3.0, -2.0, -3.0, -4.0, 1.0, -1.0, 0.5], id="close-to-rsu"),
]


@pytest.mark.parametrize("state", MEASUREMENT_STATES)
def test_rsu_range_bearing_jacobian(state: list[float]) -> None:
    model = RsuRangeBearing(RSU_POSITIONS, range_std=0.6, bearing_std=0.01)
    x = np.array(state)
    numeric = central_difference(lambda s: model.predict(s[None, :])[0], x, model.angle_mask)
    assert_jacobian_matches(model.jacobian(x[None, :])[0], numeric)


@pytest.mark.parametrize("state", MEASUREMENT_STATES)
def test_rsu_range_jacobian(state: list[float]) -> None:
    model = RsuRange(RSU_POSITIONS, range_std=0.6)
    x = np.array(state)
    numeric = central_difference(lambda s: model.predict(s[None, :])[0], x, model.angle_mask)
    assert_jacobian_matches(model.jacobian(x[None, :])[0], numeric)


@pytest.mark.parametrize(
    "state",
    [
        pytest.param([0.0, 10.0, 0.5, 0.0, 2.0, -1.5, 0.0, 0.0], id="moving"),
        pytest.param([0.0, -3.0, 2.0, 0.0, 4.0, 1.0, 0.0, 0.0], id="moving-west"),
        pytest.param([0.0, 0.2, 0.5, 0.0, -0.1, 0.3, 0.0, 0.0], id="slow"),
        pytest.param([0.0, 0.03, 0.5, 0.0, -0.04, 0.3, 0.0, 0.0], id="below-min-speed"),
    ],
)
def test_gyro_yaw_rate_jacobian(state: list[float]) -> None:
    model = GyroYawRate(std=0.005, min_speed=0.1)
    x = np.array(state)
    numeric = central_difference(lambda s: model.predict(s[None, :])[0], x, model.angle_mask, rel_step=1e-7)
    assert_jacobian_matches(model.jacobian(x[None, :])[0], numeric)


def test_measurement_jacobians_are_batched_row_by_row() -> None:
    rng = np.random.default_rng(5)
    states = rng.normal(0.0, 20.0, (6, 8))
    model: MeasurementModel
    for model in (
        RsuRangeBearing(RSU_POSITIONS, 0.6, 0.01),
        RsuRange(RSU_POSITIONS, 0.6),
        GyroYawRate(0.005),
    ):
        batched = model.jacobian(states)
        for row, state in zip(batched, states):
            np.testing.assert_array_equal(row, model.jacobian(state[None, :])[0])
