"""rsu_imu integrity: a faulty RSU is detected and excluded, or raises the alarm without exclusion; the
sub-filter bank survives the session's bytes exactly; no misleading fix in a faulty run."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.eval.rsu_imu_montecarlo import initial_state
from edgepos.pipelines import lag
from edgepos.pipelines.integrity import EXCLUDED
from edgepos.pipelines.plausibility import unwrap
from edgepos.pipelines.registry import get_pipeline
from edgepos.pipelines.rsu_imu import _decode
from edgepos.sim.faults import RsuFaults, inject
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs


@pytest.fixture(scope="module")
def scene():
    scenario = rsu_imu_paper_scenario()
    return scenario, environment(scenario), get_pipeline("rsu_imu")


def _faulty_run(scenario, offset: float = 0.05, seed: int = 14):
    """A run with one RSU's bearing off by ``offset`` rad for 10 s (a 5 m range step fails the gate)."""
    observations = [o for epoch in rsu_imu_epochs(scenario, np.random.default_rng(seed)) for o in epoch]
    faults = RsuFaults(run_fraction=1.0, range_bias_m=0.0, bearing_offset_rad=offset, duration_s=10.0)
    return inject(observations, faults, np.random.default_rng([seed, 2]))


def _run(scene, observations, **options):
    scenario, env, pipeline = scene
    state = pipeline.create(pipeline.resolve_options({"integrity": True, **options}), initial_state(scenario))
    fixes, state = pipeline.process(state, observations, env)
    return fixes, state


def test_a_bearing_offset_is_detected_excluded_and_never_misleads(scene):
    scenario = scene[0]
    observations, event = _faulty_run(scenario)
    assert event is not None
    fixes, _ = _run(scene, observations)
    excluded = [
        use.index
        for fix in fixes
        for use in fix.measurements
        if use.reason is not None and use.reason.startswith(EXCLUDED)
    ]
    assert any(observations[i].rsu_id == event.rsu_id and event.active(observations[i].t) for i in excluded)
    truth = scenario.truth
    for k, fix in enumerate(fixes):
        error = float(np.hypot(fix.x - truth.x[k + 1], fix.y - truth.y[k + 1]))
        assert fix.integrity != "ok" or error <= fix.protection_level, (fix.t, error, fix.protection_level)


def test_without_exclusion_a_detected_fault_raises_the_alarm(scene):
    scenario = scene[0]
    observations, event = _faulty_run(scenario)
    fixes, _ = _run(scene, observations, fault_exclusion=False)
    during = [fix for fix in fixes if event.active(fix.t)]
    before = [fix for fix in fixes if 2.0 <= fix.t < event.start]
    assert any(fix.integrity == "alarm" for fix in during)
    assert all(fix.integrity == "ok" for fix in before)


def test_the_bank_survives_the_state_bytes_and_batches_split_anywhere(scene):
    scenario, env, pipeline = scene
    observations, _ = _faulty_run(scenario)
    whole, state = _run(scene, observations)
    inner = unwrap(lag._unpack(state).current)[1]  # the rsu_imu session inside the lag window and envelope
    assert _decode(inner).integrity_bank is not None
    assert _decode(inner).to_bytes() == inner
    split = len(observations) // 2
    first, state = _run(scene, observations[:split])
    second, _ = pipeline.process(state, observations[split:], env)
    joined = first + second
    assert [(f.x, f.y, f.protection_level, f.integrity) for f in joined] == [
        (f.x, f.y, f.protection_level, f.integrity) for f in whole
    ]
