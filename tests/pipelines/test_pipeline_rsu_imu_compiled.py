"""rsu_imu on the compiled kernels equals rsu_imu on the numpy reference, fix for fix.

The paper's scenario (its lane change and U-turn included, so bearings and headings wrap) runs
through the pipeline twice: once as configured, on the compiled stepper, and once with
``EDGEPOS_NUMBA=0`` on the numpy reference. Every fix field must agree to rounding and every
measurement must be used or rejected alike.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from edgepos.pipelines import rsu_imu
from edgepos.pipelines.base import InitialState, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs

EPOCHS = 800  # the whole 40 s
FIELDS = ("x", "y", "vx", "vy", "speed", "yaw_rate", "nis")
#: Per-model states agree to ~1e-12 per step (tests/core/test_core_compiled.py); over 800 epochs of
#: feedback through the filter rounding differences stay below this.
TOLERANCE = 1e-9


@pytest.fixture(scope="module")
def scenario():
    return rsu_imu_paper_scenario()


@pytest.fixture(scope="module")
def observations(scenario):
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(3))[:EPOCHS]
    corrupted = []
    for k, epoch in enumerate(epochs):
        if k % 97 == 50:  # now and then a gross range outlier on one RSU, for the gate
            first = epoch[0]
            assert first.kind == "rsu"
            epoch = [dataclasses.replace(first, range=first.range + 40.0), *epoch[1:]]
        corrupted.extend(epoch)
    return corrupted


def run(scenario, observations, options, initial: bool):
    pipeline = get_pipeline("rsu_imu")
    env = StaticEnvironment({rsu.id: rsu for rsu in scenario.rsus})
    x0 = scenario.initial_state
    start = InitialState(x=x0[0], y=x0[3], vx=x0[1], vy=x0[4]) if initial else None
    state = pipeline.create(pipeline.resolve_options(options), start)
    fixes = []
    for first in range(0, len(observations), 100):  # batches of 20 epochs, state through bytes
        new, state = pipeline.process(state, observations[first : first + 100], env)
        fixes.extend(new)
    return fixes


def run_both(scenario, observations, options, monkeypatch, initial=True):
    rsu_imu._stepper.cache_clear()
    bank = rsu_imu._bank(rsu_imu._options_key(get_pipeline("rsu_imu").resolve_options(options)))
    assert rsu_imu._stepper(bank).compiled
    fast = run(scenario, observations, options, initial)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    rsu_imu._stepper.cache_clear()
    assert not rsu_imu._stepper(bank).compiled
    slow = run(scenario, observations, options, initial)
    monkeypatch.delenv("EDGEPOS_NUMBA")
    rsu_imu._stepper.cache_clear()
    return fast, slow


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"rsu_handling": "average"},
        {"priority": []},
        {"filter": "ukf", "priority": []},
        {"filter": "ekf", "priority": [], "rsu_handling": "average"},
        {"models": ["cv", "ct", "at"], "priority": ["cv"]},
        {"models": ["at"], "priority": []},
        {"models": ["singer"], "priority": [], "gate_probability": 0.0},
    ],
    ids=[
        "2imm-ckf",
        "2imm-ckf-avg",
        "imm-ckf",
        "imm-ukf",
        "imm-ekf-avg",
        "cv-ct-at",
        "at-ckf",
        "singer-nogate",
    ],
)
def test_compiled_pipeline_equals_the_numpy_reference(scenario, observations, options, monkeypatch) -> None:
    fast, slow = run_both(scenario, observations, options, monkeypatch, initial=options != {"priority": []})
    assert len(fast) == len(slow) == EPOCHS
    gated = [use for fix in slow for use in fix.measurements if "failed the gate" in (use.reason or "")]
    assert bool(gated) == (options.get("gate_probability", 1.0) > 0.0)
    for a, b in zip(fast, slow):
        assert (a.t, a.status, a.nis_dof) == (b.t, b.status, b.nis_dof)
        assert a.measurements == b.measurements
        for name in FIELDS:
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None) == (y is None), name
            if x is not None:
                assert abs(x - y) <= TOLERANCE * max(1.0, abs(y)), (name, a.t, x, y)
        np.testing.assert_allclose(a.state, b.state, rtol=TOLERANCE, atol=TOLERANCE)
        np.testing.assert_allclose(a.state_cov, b.state_cov, rtol=TOLERANCE, atol=TOLERANCE)
        np.testing.assert_allclose(
            list(a.model_probabilities.values()), list(b.model_probabilities.values()), atol=TOLERANCE
        )
