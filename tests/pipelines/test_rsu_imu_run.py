"""Runs of usual rsu_imu epochs in one compiled call (pipelines/rsu_imu_run.py) against the per-epoch path:
the same fixes and the same state bytes, to the last bit, through faults the monitor detects and
excludes, a range step the gate refuses, RSUs entering and leaving view, and batches of every size."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from edgepos.core import compiled_run
from edgepos.core.compiled import compiled_enabled
from edgepos.eval.rsu_imu_montecarlo import initial_state
from edgepos.pipelines import rsu_imu, rsu_imu_run
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.faults import RsuFaults, inject
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytestmark = pytest.mark.skipif(not compiled_enabled(), reason="runs step on the compiled kernels only")

SCENARIO = rsu_imu_paper_scenario()
ENV = environment(SCENARIO)


def observations(seed: int, faults: RsuFaults | None = None) -> list:
    run = [o for epoch in rsu_imu_epochs(SCENARIO, np.random.default_rng(seed)) for o in epoch]
    return run if faults is None else inject(run, faults, np.random.default_rng([seed, 2]))[0]


def first_ranges_off(observed: list) -> list:
    """``observed`` with each RSU's first range 40 m off: the gate refuses an RSU at the very epoch the
    monitor's bank would spawn its sub-filter."""
    seen: set[str] = set()
    out = []
    for o in observed:
        if o.kind == "rsu" and o.rsu_id not in seen:
            seen.add(o.rsu_id)
            o = dataclasses.replace(o, range=o.range + 40.0)
        out.append(o)
    return out


def filtered(
    monkeypatch, runs: bool, observed: list, batch_epochs: int, options: dict
) -> tuple[list, bytes, int]:
    """The fixes and final state of ``observed`` sent in batches of ``batch_epochs`` epochs (20 Hz), with
    runs on or off; and how many epochs the runs did."""
    if not runs:  # the per-epoch path alone: run_fixes not even looked at (its scan makes the bank's plans)
        monkeypatch.setattr(rsu_imu, "run_fixes", lambda *arguments: [])
    done = 0
    original = compiled_run.run_epochs

    def counted(*args, **kwargs):
        nonlocal done
        result = original(*args, **kwargs)
        done += result[0]
        return result

    monkeypatch.setattr(rsu_imu_run, "run_epochs", counted)
    pipeline = get_pipeline("rsu_imu")
    state = pipeline.create(pipeline.resolve_options(options), initial_state(SCENARIO))
    fixes = []
    times = sorted({o.t for o in observed})
    for first in range(0, len(times), batch_epochs):
        chosen = set(times[first : first + batch_epochs])
        fixes_now, state = pipeline.process(state, [o for o in observed if o.t in chosen], ENV)
        fixes += fixes_now
    return fixes, state, done


#: A CA-only bank with the RSUs averaged: its protection level exceeds the 1.5 m alert limit in about a
#: quarter of the paper scene's epochs, with every test passed.
ONE_MODEL_AVERAGED = {"models": ["ca"], "priority": [], "rsu_handling": "average"}

CASES = {
    "defaults": ({}, None),
    "monitor off": ({"integrity": False}, None),
    "gate off": ({"gate_probability": 0.0}, None),
    "averaged updates": ({"rsu_handling": "average"}, None),
    "a bearing fault the monitor excludes": (
        {},
        RsuFaults(run_fraction=1.0, range_bias_m=0.0, bearing_offset_rad=0.05, duration_s=10.0),
    ),
    "a bearing fault raising the alarm": (
        {"fault_exclusion": False},
        RsuFaults(run_fraction=1.0, range_bias_m=0.0, bearing_offset_rad=0.05, duration_s=10.0),
    ),
    "a range step the gate refuses": (
        {},
        RsuFaults(run_fraction=1.0, range_bias_m=5.0, bearing_offset_rad=0.0, duration_s=10.0),
    ),
    "a one-model averaged bank, its level often beyond the alert limit": (ONE_MODEL_AVERAGED, None),
}


@pytest.mark.parametrize("batch_epochs", [20, 7])
@pytest.mark.parametrize("case", [*CASES, "a new RSU's first range refused by the gate"])
def test_runs_give_the_per_epoch_paths_fixes_and_state_bit_for_bit(monkeypatch, case, batch_epochs) -> None:
    if case in CASES:
        options, faults = CASES[case]
        observed = observations(14, faults)
    else:
        options, observed = {}, first_ranges_off(observations(14))
    fixes, state, done = filtered(monkeypatch, True, observed, batch_epochs, options)
    reference_fixes, reference_state, reference_done = filtered(
        monkeypatch, False, observed, batch_epochs, options
    )
    assert reference_done == 0
    assert done > len(fixes) // 2, "most epochs should go in runs"
    assert state == reference_state
    assert len(fixes) == len(reference_fixes)
    for fix, reference in zip(fixes, reference_fixes):
        assert fix == reference, fix.t


def test_one_epoch_batches_never_run(monkeypatch) -> None:
    fixes, _, done = filtered(monkeypatch, True, observations(3)[:200], 1, {})
    assert fixes and done == 0


def test_a_run_goes_on_where_rsus_come_into_use_change_order_or_are_pruned(monkeypatch) -> None:
    """The monitor's bank spawns, re-plans and prunes inside a run (core.integrity_run), so a batch is
    not cut into several runs there; the bit-for-bit test above holds what it computes."""
    changes = {"spawned": 0, "pruned": 0, "runs": 0}
    original = rsu_imu_run.integrity_run.after_run

    def watched(bank, monitor, names):
        before = list(bank.ids)
        original(bank, monitor, names)
        changes["runs"] += 1
        changes["spawned"] += bool(set(bank.ids) - set(before))
        changes["pruned"] += bool(set(before) - set(bank.ids))

    monkeypatch.setattr(rsu_imu_run.integrity_run, "after_run", watched)
    fixes, _, done = filtered(monkeypatch, True, observations(14), 20, {})
    assert changes["spawned"] > 0 and changes["pruned"] > 0
    batches = len(fixes) // 20
    assert changes["runs"] <= batches + batches // 4, "a run per batch, or about"
    assert done > 0.9 * len(fixes)


def test_a_run_goes_on_through_fixes_in_alarm(monkeypatch) -> None:
    """A level beyond the alert limit with every test passed changes only the fix's state: the run steps
    on through it (the bit-for-bit test above holds the fixes to the per-epoch path's)."""
    fixes, _, done = filtered(monkeypatch, True, observations(14), 20, ONE_MODEL_AVERAGED)
    alarms = sum(fix.integrity == "alarm" for fix in fixes)
    assert alarms > len(fixes) // 10
    assert done > len(fixes) - len(fixes) // 20


def test_the_warm_up_tabulates_every_bound_a_monitored_run_uses(monkeypatch) -> None:
    from edgepos.core.integrity_bank import budget_tables
    from edgepos.core.integrity_run import stacked_tables
    from edgepos.pipelines.integrity import warm_up_tables

    warm_up_tables()
    misses = budget_tables.cache_info().misses, stacked_tables.cache_info().misses
    fixes, _, done = filtered(monkeypatch, True, observations(14)[:1000], 20, {})
    assert done > 0 and fixes[-1].protection_level is not None
    assert (budget_tables.cache_info().misses, stacked_tables.cache_info().misses) == misses


def perturbed(seed: int, epochs: int, dropout: float, jitter: float, gap: tuple[float, float]) -> list:
    """The first ``epochs`` epochs of a run of the paper's scene, each RSU observation dropped with
    probability ``dropout``, every epoch's time moved by up to ``jitter`` s, none in the ``gap``
    (start, length in s): RSUs leave and return, runs meet gaps and re-initialisations."""
    rng = np.random.default_rng([seed, 9])
    kept = []
    start, length = gap
    for epoch in rsu_imu_epochs(SCENARIO, np.random.default_rng(seed))[:epochs]:
        shift = float(rng.uniform(-jitter, jitter))
        for o in epoch:
            if start <= o.t < start + length or (o.kind == "rsu" and rng.random() < dropout):
                continue
            kept.append(dataclasses.replace(o, t=o.t + shift))
    return kept


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 10_000),
    batch_epochs=st.integers(2, 30),
    dropout=st.sampled_from([0.0, 0.1, 0.4]),
    jitter=st.sampled_from([0.0, 0.002]),
    gap=st.tuples(st.floats(2.0, 12.0), st.sampled_from([0.0, 0.3, 1.5])),
    options=st.fixed_dictionaries(
        {
            "integrity": st.booleans(),
            "gate_probability": st.sampled_from([0.0, 0.99]),
            "rsu_handling": st.sampled_from(["joint", "average"]),
            "fault_exclusion": st.booleans(),
            "alert_limit_m": st.sampled_from([1.5, 0.8]),  # 0.8: half the joint fixes in alarm, all averaged
        }
    ),
    fault=st.sampled_from([None, (5.0, 0.0), (0.0, 0.05)]),
)
def test_runs_give_the_per_epoch_paths_fixes_on_any_batching_and_losses(
    seed, batch_epochs, dropout, jitter, gap, options, fault
) -> None:
    observed = perturbed(seed, 300, dropout, jitter, gap)
    if fault is not None:
        faults = RsuFaults(
            run_fraction=1.0, range_bias_m=fault[0], bearing_offset_rad=fault[1], duration_s=5.0
        )
        observed = inject(observed, faults, np.random.default_rng([seed, 2]))[0]
    with pytest.MonkeyPatch.context() as patch:
        fixes, state, done = filtered(patch, True, observed, batch_epochs, options)
    with pytest.MonkeyPatch.context() as patch:
        reference_fixes, reference_state, _ = filtered(patch, False, observed, batch_epochs, options)
    assert done > 0
    assert state == reference_state
    assert fixes == reference_fixes


def tracking_state_and_batch() -> tuple[bytes, list]:
    """The bare pipeline's state after 40 epochs of the paper scene (tracking, on the runs' path), and its
    next 20 epochs. (The registry's plausibility wrapper filters a batch that fails again in smaller
    parts, and a lone epoch takes the per-epoch path.)"""
    pipeline = rsu_imu.RsuImuPipeline()
    state = pipeline.create(pipeline.resolve_options({}), initial_state(SCENARIO))
    observed = observations(3)
    times = sorted({o.t for o in observed})
    for first in (0, 20):
        chosen = set(times[first : first + 20])
        _, state = pipeline.process(state, [o for o in observed if o.t in chosen], ENV)
    chosen = set(times[40:60])
    return state, [o for o in observed if o.t in chosen]


@pytest.mark.parametrize(
    ("values", "bounded"),
    [
        ([0.0, -3.5, 1e149], True),
        ([0.0, float("nan")], False),
        ([float("-inf"), 1.0], False),
        ([1e150, 0.0], False),  # at the bound: out
        ([-2e150], False),
    ],
)
def test_the_runs_bound_test(values, bounded):
    """``kernels_run._bounded``: what a run's epoch must pass for its fix to be made in the run."""
    from edgepos.core import kernels_run

    assert kernels_run._bounded(np.array(values), compiled_run.FIX_INPUT_BOUND) is bounded


def test_an_epoch_beyond_the_bound_goes_the_per_epoch_path(monkeypatch):
    """A run stops before an epoch whose fix would be made of a number beyond ``FIX_INPUT_BOUND`` (NaN
    included), and the per-epoch path, which checks every fix number by number, makes it: with the bound
    forced below every output no run does an epoch, and the fixes and state are the same."""
    state, batch = tracking_state_and_batch()
    expected = rsu_imu.RsuImuPipeline().process(state, batch, ENV)
    done = []
    original = compiled_run.run_epochs

    def counted(*args, **kwargs):
        result = original(*args, **kwargs)
        done.append(result[0])
        return result

    monkeypatch.setattr(rsu_imu_run, "run_epochs", counted)
    assert rsu_imu.RsuImuPipeline().process(state, batch, ENV) == expected
    assert done and sum(done) >= rsu_imu_run.MIN_RUN  # the runs' path is taken...
    done.clear()
    monkeypatch.setattr(compiled_run, "FIX_INPUT_BOUND", 1e-3)
    assert rsu_imu.RsuImuPipeline().process(state, batch, ENV) == expected
    assert done and sum(done) == 0  # ...and with the bound below every output, no run does an epoch


def test_the_used_records_are_kept_by_index(monkeypatch):
    """``used_records`` holds record ``i`` at index ``i`` of each kind, grows with the count asked for up to
    ``USED_KEPT``, and ``used`` gives the very same records there and new equal ones beyond."""
    monkeypatch.setattr(rsu_imu_run, "_USED", {})
    monkeypatch.setattr(rsu_imu_run, "USED_KEPT", 6)
    short = rsu_imu_run.used_records("rsu", 3)
    assert [(u.index, u.kind, u.used) for u in short] == [(i, "rsu", True) for i in range(3)]
    longer = rsu_imu_run.used_records("rsu", 100)
    assert len(longer) == 6 and longer[:3] == short and all(a is b for a, b in zip(short, longer))
    assert [u.index for u in rsu_imu_run.used_records("gyro", 2)] == [0, 1]
    assert rsu_imu_run.used(4, "rsu") is longer[4] and rsu_imu_run.used(1, "gyro").kind == "gyro"
    beyond = rsu_imu_run.used(9, "rsu")
    assert (beyond.index, beyond.kind, beyond.used) == (9, "rsu", True) and len(
        rsu_imu_run.used_records("rsu", 9)
    ) == 6


@pytest.mark.parametrize("count", [1, 2, 3, 4, 6])
def test_the_runs_weighted_nis_is_the_per_epoch_dot(count):
    """``run_outputs``' NIS weighted by the model probabilities, every epoch in one matmul, is bit for bit
    ``probabilities.dot(nis)`` per epoch (``rsu_imu._step``'s), over magnitudes 1e-8 .. 1e8 of both signs."""
    import types

    rng = np.random.default_rng(count)
    nc, size = 8, 40
    stepper = types.SimpleNamespace(_sizes=(count, nc), _prediction_size=size)
    width = 2 * size + 73 * count + nc * (1 + nc)  # past the fused covariance and the NIS
    for _ in range(50):
        outs = rng.standard_normal((20, width)) * 10.0 ** rng.integers(-8, 9, (20, width))
        done = int(rng.integers(1, 21))
        _, _, probabilities, weighted = compiled_run.run_outputs(stepper, outs, done)
        nis = outs[:done, 2 * size + count : 2 * size + 2 * count]
        expected = [float(np.array(p).dot(n)) for p, n in zip(probabilities, nis)]
        assert len(weighted) == done and all(type(w) is float for w in weighted)
        assert np.array(weighted).tobytes() == np.array(expected).tobytes()
