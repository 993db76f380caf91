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
from edgepos.core.compiled import BankStepper, CompiledBankStepper
from edgepos.pipelines import rsu_imu, rsu_imu_run
from edgepos.pipelines.base import InitialState, StaticEnvironment
from edgepos.pipelines.integrity import EXCLUDED
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


@pytest.mark.parametrize(
    "options",
    [{}, {"integrity": False}, {"filter": "ekf", "rsu_handling": "average"}, {"fault_exclusion": False}],
    ids=["default", "no-monitor", "ekf-avg", "no-exclusion"],
)
def test_the_one_call_epoch_gives_the_per_call_paths_fixes_and_states(scenario, options, monkeypatch) -> None:
    """``CompiledBankStepper.step`` (prediction, gate and correction in one compiled call) against the
    per-call path (its ``step`` replaced by the reference stepper's, which only predicts): the same fixes
    and states, bit for bit. The observations carry gross outliers for the gate and, from epoch 300, a
    range bias of 2 m on one RSU that the monitor excludes; the one call decides the other epochs."""
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(4))[:400]
    observations = []
    for k, epoch in enumerate(epochs):
        first = epoch[0]
        if k % 97 == 50:
            epoch = [dataclasses.replace(first, range=first.range + 40.0), *epoch[1:]]
        elif k >= 300 and first.kind == "rsu":
            epoch = [dataclasses.replace(first, range=first.range + 2.0), *epoch[1:]]
        observations.extend(epoch)
    decided = []
    one_call = CompiledBankStepper.step

    def counted(self, *arguments):
        prediction, result = one_call(self, *arguments)
        decided.append(result is not None)
        return prediction, result

    rsu_imu._stepper.cache_clear()
    monkeypatch.setattr(rsu_imu_run, "MIN_RUN", 10**9)  # every epoch on its own (runs: test_rsu_imu_run.py)
    monkeypatch.setattr(CompiledBankStepper, "step", counted)
    fast = run_states(scenario, observations, options)
    monkeypatch.setattr(CompiledBankStepper, "step", BankStepper.step)
    slow = run_states(scenario, observations, options)
    rsu_imu._stepper.cache_clear()
    assert fast == slow
    assert sum(decided[:300]) >= 300 - 4 and not all(decided)  # before the bias: all but the outliers' epochs
    reasons = [use.reason or "" for fixes, _ in slow for fix in fixes for use in fix.measurements]
    assert any("failed the gate" in reason for reason in reasons)
    assert any(reason.startswith(EXCLUDED) for reason in reasons) == (
        options.get("integrity", True) and options.get("fault_exclusion", True)
    )


def run_states(scenario, observations, options) -> list[tuple[list, bytes]]:
    """Every batch's fixes and state (batches of 20 epochs, from the scenario's initial state)."""
    pipeline = get_pipeline("rsu_imu")
    env = StaticEnvironment({rsu.id: rsu for rsu in scenario.rsus})
    x0 = scenario.initial_state
    state = pipeline.create(pipeline.resolve_options(options), InitialState(x0[0], x0[3], x0[1], x0[4]))
    batches = []
    for first in range(0, len(observations), 100):
        fixes, state = pipeline.process(state, observations[first : first + 100], env)
        batches.append((fixes, state))
    return batches
