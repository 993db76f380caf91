"""The default rsu_imu pipeline on the paper's simulated scenario (sec. 5): accuracy end to end."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.pipelines.base import InitialState, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs

SECONDS = 10.0


@pytest.fixture(scope="module")
def scenario():
    return rsu_imu_paper_scenario()


@pytest.fixture(scope="module")
def epochs(scenario):
    count = round(SECONDS / scenario.period)
    return rsu_imu_epochs(scenario, np.random.default_rng(20250101))[:count]


def run(scenario, epochs, options=None, initial=True):
    pipeline = get_pipeline("rsu_imu")
    env = StaticEnvironment({rsu.id: rsu for rsu in scenario.rsus})
    x0 = scenario.initial_state  # [xp, xv, xa, yp, yv, ya, phi, omega]
    start = (
        InitialState(x=x0[0], y=x0[3], vx=x0[1], vy=x0[4], position_std=0.5, velocity_std=0.5)
        if initial
        else None
    )
    state = pipeline.create(pipeline.resolve_options(options), start)
    fixes, state = pipeline.process(state, [o for e in epochs for o in e], env)
    assert len(fixes) == len(epochs)
    truth = scenario.truth
    k = np.arange(1, len(epochs) + 1)
    assert np.allclose([f.t for f in fixes], truth.t[k])
    errors = np.hypot(
        [f.x - x for f, x in zip(fixes, truth.x[k])], [f.y - y for f, y in zip(fixes, truth.y[k])]
    )
    return fixes, errors


def test_default_pipeline_reaches_paper_accuracy_over_10_s(scenario, epochs) -> None:
    fixes, errors = run(scenario, epochs)
    rmse = math.sqrt(float(np.mean(errors**2)))
    assert rmse < 0.3, f"position RMSE {rmse:.3f} m"
    assert all(f.status == "tracking" for f in fixes)
    # the manoeuvres of the first 10 s (speed-up at 4 s, lane change at 8 s) are followed too
    assert float(np.max(errors)) < 1.0


def test_self_initialised_pipeline_converges_on_the_scenario(scenario, epochs) -> None:
    fixes, errors = run(scenario, epochs, initial=False)
    assert fixes[0].status == "initialised"
    settled = errors[len(errors) // 2 :]
    assert math.sqrt(float(np.mean(settled**2))) < 0.3
