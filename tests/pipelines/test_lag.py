"""The lag window (``pipelines.lag.LagWindow``) around every registered pipeline: late measurements inside
the window give the state and fixes time order gives, whatever the order of arrival (a hypothesis property
on rsu_imu, fixed shuffles on the other pipelines); revised fixes; too-late measurements reported unused;
the option bounds (max_delay_s, max_window_epochs, max_lead_s); the state format and its size; track()."""

from __future__ import annotations

import dataclasses
import math
import random
import typing
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from edgepos.core import state as state_format
from edgepos.core.observations import (
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    PseudorangeObservation,
    RissObservation,
    RsuObservation,
    RsuRangeObservation,
    V2vRangeObservation,
)
from edgepos.core.state import StateFormatError
from edgepos.eval.federated import assisting_tracks
from edgepos.eval.rsu_imu_montecarlo import initial_state
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
from edgepos.pipelines import lag, lag_state, plausibility, rsu_imu
from edgepos.pipelines.base import (
    Environment,
    Fix,
    InitialState,
    Pipeline,
    PipelineInputError,
    StaticEnvironment,
)
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.delivery import arrival_batches
from edgepos.sim.federated import make_run as federated_run
from edgepos.sim.scenarios import rsu_imu_paper_scenario, staggered_rsus
from edgepos.sim.sensors import environment, rsu_imu_epochs
from edgepos.sim.trajectory import Cruise, build_trajectory
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from test_v2v_coop import epoch as v2v_epoch
from test_v2v_coop import track as v2v_track

SEED = 2024
EPOCHS = 40
MAX_DELAY_S = 1.0  # the default window
GNSS_DATA = Path(__file__).resolve().parents[1] / "data" / "gnss-rover"

SCENARIO = rsu_imu_paper_scenario()
RSU_ENV = environment(SCENARIO)
INITIAL = initial_state(SCENARIO)
RSU_IMU = get_pipeline("rsu_imu")
RSU_EPOCHS = rsu_imu_epochs(SCENARIO, np.random.default_rng([SEED, 0]))[:EPOCHS]
RSU_OBSERVATIONS = [o for epoch in RSU_EPOCHS for o in epoch]


# -- helpers ----------------------------------------------------------------------------------------
def new_session(
    pipeline: Pipeline, options: dict | None = None, initial: InitialState | None = None
) -> bytes:
    return pipeline.create(pipeline.resolve_options(options), initial)


def rsu_session(**options) -> bytes:
    return new_session(RSU_IMU, options, INITIAL)


def feed(
    pipeline: Pipeline, state: bytes, batches: Sequence[Sequence[Observation]], env: Environment
) -> tuple[bytes, list[list[Fix]]]:
    """Send ``batches`` in order: the final state and each response's fixes."""
    responses = []
    for batch in batches:
        fixes, state = pipeline.process(state, list(batch), env)
        responses.append(fixes)
    return state, responses


def last_fixes(responses: Sequence[Sequence[Fix]]) -> dict[float, Fix]:
    """The last fix a client received for each epoch."""
    latest: dict[float, Fix] = {}
    for fixes in responses:
        for fix in fixes:
            latest[fix.t] = fix
    return latest


def current(state: bytes) -> bytes:
    return lag._unpack(state).current


def assert_close(a: typing.Any, b: typing.Any, path: str = "state", tol: float = 1e-9) -> None:
    """Equal structures, numbers equal to ``tol`` (absolute, or relative for large ones)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for key in a:
            assert_close(a[key], b[key], f"{path}.{key}", tol)
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        assert a.shape == b.shape, path
        np.testing.assert_allclose(a, b, rtol=tol, atol=tol, err_msg=path)
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_close(x, y, f"{path}[{i}]", tol)
    elif isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
        if math.isnan(a):
            assert math.isnan(b), path
        else:
            assert math.isclose(a, b, rel_tol=tol, abs_tol=tol), (path, a, b)
    else:
        assert a == b, (path, a, b)


def decoded(inner: bytes) -> tuple[dict[str, typing.Any], dict[str, np.ndarray]]:
    """A pipeline's state as its numbers: rsu_imu's binary layout, or ``core.state``'s (the others)."""
    if inner[: len(rsu_imu._MAGIC)] != rsu_imu._MAGIC:
        return state_format.unpack(inner)
    session = rsu_imu._decode(inner)
    meta = {k: getattr(session, k) for k in ("options", "initialised", "t", "filter_t", "epochs")}
    return meta, {"probabilities": session.probabilities, "means": session.means, "covs": session.covs}


def assert_same_filter_state(got: bytes, want: bytes, tol: float = 1e-9) -> None:
    """The inner states (plausibility envelope + pipeline state) byte-identical, or their decoded numbers
    equal to ``tol`` (an epoch's measurements may be stacked in another order: round-off)."""
    got_current, want_current = current(got), current(want)
    if got_current == want_current:
        return
    got_envelope, got_inner = plausibility.unwrap(got_current)
    want_envelope, want_inner = plausibility.unwrap(want_current)
    assert_close(dataclasses.asdict(got_envelope), dataclasses.asdict(want_envelope), "envelope", tol)
    got_meta, got_arrays = decoded(got_inner)
    want_meta, want_arrays = decoded(want_inner)
    assert_close(got_meta, want_meta, "meta", tol)
    assert_close(got_arrays, want_arrays, "arrays", tol)


def assert_fix_close(got: Fix, want: Fix, tol: float = 1e-9) -> None:
    assert got.t == want.t
    for name in ("x", "y", "vx", "vy"):
        assert math.isclose(getattr(got, name), getattr(want, name), rel_tol=tol, abs_tol=tol), (got.t, name)


def check_responses(batches: Sequence[Sequence[Observation]], responses: Sequence[Sequence[Fix]]) -> None:
    """Each response in time order, one fix per epoch; revised fixes exactly for the epochs answered before
    at or after the batch's earliest late measurement (none without late data); every measurement of the
    batch reported once, in the fix of its own epoch. (For deliveries with nothing too late.)"""
    answered: set[float] = set()
    newest: float | None = None
    for batch, fixes in zip(batches, responses, strict=True):
        times = [fix.t for fix in fixes]
        assert times == sorted(set(times)), times
        late = [o.t for o in batch if newest is not None and o.t <= newest]
        earliest = min(late) if late else math.inf
        for fix in fixes:
            if fix.revised:
                assert fix.t in answered and fix.t >= earliest, (fix.t, earliest)
            else:
                assert fix.t not in answered, fix.t
        assert {fix.t for fix in fixes if fix.revised} == {t for t in answered if t >= earliest}
        reported = sorted((use.index, use.kind, fix.t) for fix in fixes for use in fix.measurements)
        assert reported == sorted((i, o.kind, o.t) for i, o in enumerate(batch))
        answered |= set(times)
        newest = max([*times, *([] if newest is None else [newest])])


# -- the in-order reference -------------------------------------------------------------------------
def _rsu_reference() -> tuple[bytes, dict[float, Fix], list[list[Fix]]]:
    state, responses = feed(RSU_IMU, rsu_session(), RSU_EPOCHS, RSU_ENV)
    return state, last_fixes(responses), responses


RSU_REF_STATE, RSU_REF_FIXES, RSU_REF_RESPONSES = _rsu_reference()


def deliver(
    delays: dict[int, float], epoch_delays: dict[int, float], batch_epochs: int, shuffle_seed: int
) -> list[list[Observation]]:
    """The paper scenario's first epochs as a vehicle sends them when measurement ``i`` arrives
    ``delays[i]`` late and every measurement of epoch ``k`` ``epoch_delays[k]`` late; each batch then
    shuffled."""
    arrivals = np.array([o.t for o in RSU_OBSERVATIONS])
    for index, delay in delays.items():
        arrivals[index] += delay
    start = 0
    for k, epoch in enumerate(RSU_EPOCHS):
        if k in epoch_delays:
            arrivals[start : start + len(epoch)] = [o.t + epoch_delays[k] for o in epoch]
        start += len(epoch)
    batches = arrival_batches(RSU_OBSERVATIONS, arrivals, batch_epochs)
    shuffler = random.Random(shuffle_seed)
    for batch in batches:
        shuffler.shuffle(batch)
    return batches


# -- 1. order invariance: rsu_imu, any arrival within the window -------------------------------------
DELAYS = st.floats(0.0, MAX_DELAY_S, allow_nan=False)


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    delays=st.dictionaries(st.integers(0, len(RSU_OBSERVATIONS) - 1), DELAYS, max_size=30),
    epoch_delays=st.dictionaries(st.integers(0, EPOCHS - 1), st.floats(0.05, MAX_DELAY_S), max_size=4),
    batch_epochs=st.integers(1, 5),
    shuffle_seed=st.integers(0, 2**32 - 1),
)
@example(
    delays={7: 0.4, 60: 0.95, 61: 0.3},
    epoch_delays={0: 0.2, 12: 0.6, 30: 0.999},
    batch_epochs=1,
    shuffle_seed=0,
)
@example(
    delays={i: MAX_DELAY_S for i in range(0, 200, 9)}, epoch_delays={39: 0.5}, batch_epochs=3, shuffle_seed=1
)
def test_rsu_imu_any_arrival_order_within_the_window_gives_the_time_order_result(
    delays, epoch_delays, batch_epochs, shuffle_seed
):
    batches = deliver(delays, epoch_delays, batch_epochs, shuffle_seed)
    state, responses = feed(RSU_IMU, rsu_session(), batches, RSU_ENV)
    assert_same_filter_state(state, RSU_REF_STATE)
    latest = last_fixes(responses)
    assert latest.keys() == RSU_REF_FIXES.keys()
    for t, fix in latest.items():
        assert_fix_close(fix, RSU_REF_FIXES[t])
    check_responses(batches, responses)
    assert not any(
        use.reason and "too late" in use.reason for r in responses for f in r for use in f.measurements
    )


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    delays=st.dictionaries(
        st.integers(0, len(RSU_OBSERVATIONS) - 1), st.floats(0.0, 1.2), min_size=1, max_size=30
    ),
    batch_epochs=st.integers(1, 4),
)
def test_rsu_imu_too_late_data_is_left_out_and_the_rest_is_time_order(delays, batch_epochs):
    """A 0.5 s window and delays up to 1.2 s: exactly the measurements older than the newest epoch before
    their batch minus max_delay_s are reported too late, and the result is time order's on the others."""
    delay = 0.5
    batches = deliver(delays, {}, batch_epochs, 0)
    state, responses = feed(RSU_IMU, rsu_session(max_delay_s=delay), batches, RSU_ENV)
    expected, reported = set(), set()
    newest = None
    for batch, fixes in zip(batches, responses, strict=True):
        expected |= {id(o) for o in batch if newest is not None and o.t < newest - delay}
        reported |= {id(batch[i]) for fix in fixes for i in too_late_uses(fix)}
        newest = max(o.t for o in batch) if newest is None else max(newest, *(o.t for o in batch))
        times = [fix.t for fix in fixes]
        assert times == sorted(set(times)) and fixes
    assert reported == expected
    kept = [[o for o in epoch if id(o) not in reported] for epoch in RSU_EPOCHS]
    reference, in_order = feed(RSU_IMU, rsu_session(max_delay_s=delay), [e for e in kept if e], RSU_ENV)
    assert_same_filter_state(state, reference)
    latest, want = last_fixes(responses), last_fixes(in_order)
    assert latest.keys() == want.keys()
    for t, fix in want.items():
        assert_fix_close(latest[t], fix)


def test_the_explicit_example_has_late_data_joining_an_epoch_and_at_a_new_epoch_time():
    """The first @example above exercises both kinds of late arrival (so the property does whatever
    hypothesis draws), and the in-order delivery's responses pass the same response checks."""
    batches = deliver({7: 0.4, 60: 0.95, 61: 0.3}, {0: 0.2, 12: 0.6, 30: 0.999}, 1, 0)
    seen: set[float] = set()
    joining = new_time = 0
    for batch in batches:
        newest = max(seen) if seen else -math.inf
        for t in {o.t for o in batch}:
            if t <= newest:
                joining += t in seen
                new_time += t not in seen
        seen |= {o.t for o in batch}
    assert joining and new_time
    check_responses(RSU_EPOCHS, RSU_REF_RESPONSES)


# -- 2. the same on the other pipelines, a few fixed shuffles -----------------------------------------
Schedule = list[tuple[int, str, int]]  # (epoch, "all" | "last" | "first", the epoch it arrives with)

SCHEDULES: dict[str, Schedule] = {
    "whole epoch late (a new epoch time)": [(3, "all", 5)],
    "the end of an epoch late (joins it)": [(4, "last", 7)],
    "several late, delivered newest first": [(6, "all", 9), (5, "last", 9), (2, "last", 4), (3, "all", 4)],
    "late data alone in a batch": [(8, "last", 10), (9, "all", 10)],
}


def scheduled(epochs: Sequence[Sequence[Observation]], schedule: Schedule) -> list[list[Observation]]:
    """Epoch batches with parts held back and sent with a later epoch's batch (after its own data; the
    late parts newest first). An entry arriving with epoch k == len(epochs) goes in a batch of its own."""
    held: dict[int, list[Observation]] = {}
    kept = [list(epoch) for epoch in epochs]
    for k, part, arrive in sorted(schedule, key=lambda entry: -entry[0]):
        count = len(kept[k]) if part == "all" else max(1, len(kept[k]) // 3)
        moved = kept[k][-count:] if part != "first" else kept[k][:count]
        kept[k] = kept[k][:-count] if part != "first" else kept[k][count:]
        held.setdefault(arrive, []).extend(moved)
    batches = [kept[k] + held.get(k, []) for k in range(len(epochs))]
    if len(epochs) in held:
        batches.append(held[len(epochs)])
    return [batch for batch in batches if batch]


def assert_order_invariant(
    pipeline: Pipeline,
    options: dict,
    initial: InitialState | None,
    epochs: Sequence[Sequence[Observation]],
    env: Environment,
    schedule: Schedule,
    exact: bool = False,
    tol: float = 1e-9,
) -> None:
    reference, in_order = feed(pipeline, new_session(pipeline, options, initial), epochs, env)
    batches = scheduled(epochs, schedule)
    assert sorted(map(id, (o for b in batches for o in b))) == sorted(map(id, (o for e in epochs for o in e)))
    state, responses = feed(pipeline, new_session(pipeline, options, initial), batches, env)
    if exact:
        assert current(state) == current(reference)
    else:
        assert_same_filter_state(state, reference, tol)
    want, got = last_fixes(in_order), last_fixes(responses)
    assert got.keys() == want.keys()
    for t, fix in want.items():
        if fix.x is None:
            assert got[t].x is None
        else:
            assert_fix_close(got[t], fix, tol)
    check_responses(batches, responses)


def _v2v() -> tuple[list[list[Observation]], StaticEnvironment]:
    env = StaticEnvironment(tracks={"north": v2v_track("north", 0.0, 30.0, 20.0)}, vehicle_id="me")
    epochs = [
        v2v_epoch(0.2 * k, 3.0 * k, 0.1 * (k % 3), {"north": math.hypot(30.0 - 3.0 * k, 20.0)})
        for k in range(12)
    ]
    return epochs, env


def _v2x() -> tuple[list[list[Observation]], StaticEnvironment]:
    run = federated_run(3, 0, "clean", steps=12)
    # The neighbours' tracks as published after the last epoch (history covering every epoch): the
    # environment must not change between the in-order run and the shuffled one.
    env = StaticEnvironment(tracks=assisting_tracks(run)[-1], vehicle_id="target")
    return [list(epoch) for epoch in run.observations], env


def _gnss() -> tuple[list[list[Observation]], StaticEnvironment]:
    codes = {system: DEFAULT_CODES[system] for system in "GC"}
    env = StaticEnvironment(
        navigation=Ephemerides.from_navigation(read_navigation(GNSS_DATA / "broadcast-nav.rnx"))
    )
    epochs: list[list[Observation]] = []
    for count, epoch in enumerate(read_epochs(GNSS_DATA / "rover-0-5min.rnx", codes)):
        if count >= 12:
            break
        epochs.append(
            [
                PseudorangeObservation(epoch.gpst % 604800.0, system, int(prn), float(pr), float(cn0))
                for system, prn, pr, cn0 in zip(
                    epoch.systems, epoch.prns, epoch.pseudorange_m, epoch.cn0_dbhz
                )
                if math.isfinite(pr) and math.isfinite(cn0)
            ]
        )
    return epochs, env


@pytest.fixture(scope="module")
def v2v_data():
    return _v2v()


@pytest.fixture(scope="module")
def v2x_data():
    return _v2x()


@pytest.fixture(scope="module")
def gnss_data():
    return _gnss()


@pytest.mark.parametrize("schedule", SCHEDULES.values(), ids=SCHEDULES.keys())
def test_v2v_coop_arrival_order_does_not_matter(v2v_data, schedule):
    epochs, env = v2v_data
    assert_order_invariant(get_pipeline("v2v_coop"), {"method": "aug_ukf"}, None, epochs, env, schedule)


def test_v2v_coop_an_epoch_stacked_in_another_order_is_the_same_to_round_off(v2v_data):
    epochs, env = v2v_data
    assert_order_invariant(
        get_pipeline("v2v_coop"), {"method": "aug_ukf"}, None, epochs, env, [(5, "first", 8)]
    )


@pytest.mark.parametrize("schedule", SCHEDULES.values(), ids=SCHEDULES.keys())
def test_v2x_federated_arrival_order_does_not_matter(v2x_data, schedule):
    epochs, env = v2x_data
    assert_order_invariant(get_pipeline("v2x_federated"), {}, None, epochs, env, schedule)


def test_v2x_federated_an_epoch_stacked_in_another_order_is_the_same_to_round_off(v2x_data):
    epochs, env = v2x_data
    assert_order_invariant(get_pipeline("v2x_federated"), {}, None, epochs, env, [(5, "first", 8)])


@pytest.mark.parametrize("filter_name", ["ukf", "pf"])
@pytest.mark.parametrize("schedule", SCHEDULES.values(), ids=SCHEDULES.keys())
def test_gnss_tight_replay_reproduces_the_time_order_state_exactly(gnss_data, filter_name, schedule):
    """1 Hz epochs, so a 5 s window; each epoch's pseudoranges keep their order (the stored ones first,
    then the late ones), so replay must give the very same bytes: the particle filter's random draws
    are seeded by the epoch count and must be drawn again identically."""
    epochs, env = gnss_data
    options = {"filter": filter_name, "particles": 200, "seed": 3, "systems": ["C", "G"], "max_delay_s": 5.0}
    assert_order_invariant(get_pipeline("gnss_tight"), options, None, epochs, env, schedule, exact=True)


def test_gnss_tight_an_epoch_stacked_in_another_order_is_the_same_to_round_off(gnss_data):
    """Pseudoranges of 2e7 m stacked in another order: round-off of about 1e-9 m, hence the looser bound."""
    epochs, env = gnss_data
    options = {"filter": "ukf", "seed": 3, "systems": ["C", "G"], "max_delay_s": 5.0}
    assert_order_invariant(
        get_pipeline("gnss_tight"), options, None, epochs, env, [(5, "first", 8)], tol=1e-6
    )


# -- 3. too late --------------------------------------------------------------------------------------
def rsu_state_after(count: int, **options) -> bytes:
    state, _ = feed(RSU_IMU, rsu_session(**options), RSU_EPOCHS[:count], RSU_ENV)
    return state


def first_rsu(k: int) -> RsuObservation:
    observation = RSU_EPOCHS[k][0]
    assert isinstance(observation, RsuObservation)
    return observation


def too_late_uses(fix: Fix) -> dict[int, str]:
    return {
        use.index: use.reason or ""
        for use in fix.measurements
        if not use.used and "too late" in (use.reason or "")
    }


def test_a_too_late_measurement_is_reported_unused_and_the_rest_of_the_batch_applied():
    state = rsu_state_after(30, max_delay_s=0.5)
    old = first_rsu(5)
    batch = [*RSU_EPOCHS[30][:2], old, *RSU_EPOCHS[30][2:]]
    fixes, new_state = RSU_IMU.process(state, batch, RSU_ENV)
    assert [f.t for f in fixes] == [RSU_EPOCHS[30][0].t] and not fixes[0].revised
    reasons = too_late_uses(fixes[-1])
    assert list(reasons) == [2]
    # How late: against the session's newest epoch before the batch, the one it was judged by.
    newest = RSU_EPOCHS[29][0].t
    assert f"{newest - old.t:.6g} s older" in reasons[2] and f"newest epoch t={newest!r}" in reasons[2]
    assert "max_delay_s 0.5" in reasons[2]
    assert all(use.used for use in fixes[-1].measurements if use.index != 2)
    # The too-late measurement changed nothing: the state is time order's without it.
    reference, _ = feed(RSU_IMU, rsu_session(max_delay_s=0.5), RSU_EPOCHS[:31], RSU_ENV)
    assert_same_filter_state(new_state, reference)
    assert_fix_close(fixes[0], RSU_REF_FIXES[RSU_EPOCHS[30][0].t])


@pytest.mark.parametrize("max_delay_s", [0.5, 1.0])
def test_a_batch_of_only_too_late_measurements_returns_the_newest_fix_with_the_report(max_delay_s):
    state = rsu_state_after(30, max_delay_s=max_delay_s)
    newest = RSU_EPOCHS[29][0].t
    batch = [first_rsu(3), RSU_EPOCHS[2][-1]]  # an RSU range and a gyro sample, both before the window
    fixes, new_state = RSU_IMU.process(state, batch, RSU_ENV)
    assert len(fixes) == 1 and fixes[0].t == newest and fixes[0].revised
    assert set(too_late_uses(fixes[0])) == {0, 1}
    assert current(new_state) == current(state)
    assert_fix_close(fixes[0], RSU_REF_FIXES[newest])


def test_the_too_late_report_names_the_lateness_exactly():
    state = rsu_state_after(30, max_delay_s=0.5)
    newest = RSU_EPOCHS[29][0].t
    for k in (0, 10, 18):
        observation = first_rsu(k)
        fixes, _ = RSU_IMU.process(state, [observation], RSU_ENV)
        reason = too_late_uses(fixes[-1])[0]
        assert f"t={observation.t!r}" in reason and f"{newest - observation.t:.6g} s older" in reason
        assert f"t={newest!r}" in reason


@pytest.mark.parametrize(
    ("late_fault", "fresh_fault"),
    [(("rsu_id", "nope"), ("range", -1.0)), (("range", -1.0), ("rsu_id", "nope"))],
    ids=["unknown RSU late, negative range fresh", "negative range late, unknown RSU fresh"],
)
def test_a_malformed_too_late_measurement_refuses_the_batch_with_the_other_problems(late_fault, fresh_fault):
    state = rsu_state_after(30, max_delay_s=0.5)
    late = dataclasses.replace(first_rsu(5), **{late_fault[0]: late_fault[1]})
    fresh = dataclasses.replace(first_rsu(30), **{fresh_fault[0]: fresh_fault[1]})
    batch = [RSU_EPOCHS[30][-1], fresh, late]
    with pytest.raises(PipelineInputError) as error:
        RSU_IMU.process(state, batch, RSU_ENV)
    problems = {(p.index, p.field) for p in error.value.problems}
    assert (2, late_fault[0]) in problems and (1, fresh_fault[0]) in problems, problems
    assert all(p.index in (1, 2) for p in error.value.problems), error.value.problems


def test_a_malformed_too_late_measurement_alone_refuses_the_batch():
    state = rsu_state_after(30, max_delay_s=0.5)
    with pytest.raises(PipelineInputError) as error:
        RSU_IMU.process(
            state, [RSU_EPOCHS[30][-1], dataclasses.replace(first_rsu(5), rsu_id="nope")], RSU_ENV
        )
    assert [(p.index, p.field) for p in error.value.problems] == [(1, "rsu_id")]


# -- 4. max_lead_s, the bounds, max_delay_s = 0 -------------------------------------------------------
def test_a_measurement_far_ahead_of_the_rest_of_its_batch_is_refused_by_index():
    state = rsu_state_after(10)
    t = RSU_EPOCHS[10][0].t
    batch = [GyroObservation(t, 0.0), GyroObservation(t + 30.0, 0.0), GyroObservation(t + 0.05, 0.0)]
    with pytest.raises(PipelineInputError) as error:
        RSU_IMU.process(state, batch, RSU_ENV)
    [problem] = error.value.problems
    assert problem.index == 1 and problem.field == "t" and "max_lead_s 10" in problem.reason
    # Within the bound (its own max_lead_s) the batch goes through.
    state = rsu_state_after(10, max_lead_s=40.0)
    fixes, _ = RSU_IMU.process(state, batch, RSU_ENV)
    assert [f.t for f in fixes] == [t, t + 0.05, t + 30.0]


def test_the_lead_of_a_lone_epoch_over_the_session_is_not_bounded():
    """max_lead_s compares a batch's measurements with each other, not with the session's clock."""
    fixes, _ = RSU_IMU.process(
        rsu_state_after(10), [GyroObservation(RSU_EPOCHS[9][0].t + 20.0, 0.0)], RSU_ENV
    )
    assert len(fixes) == 1


@pytest.mark.parametrize(
    ("name", "bad", "good"),
    [
        ("max_delay_s", [-0.1, 10.5, math.nan, "1"], [0.0, 10.0]),
        ("max_window_epochs", [0, 1001, 2.5], [1, 1000]),
        ("max_lead_s", [0.5, 3601.0, -1.0], [1.0, 3600.0]),
    ],
)
def test_window_option_bounds(name, bad, good):
    for value in bad:
        with pytest.raises(PipelineInputError) as error:
            RSU_IMU.resolve_options({name: value})
        assert any(name in p.field for p in error.value.problems), (value, error.value.problems)
    for value in good:
        assert RSU_IMU.resolve_options({name: value})[name] == value
    with pytest.raises(PipelineInputError) as error:
        RSU_IMU.resolve_options({name: bad[0], "models": "nope"})
    assert len(error.value.problems) >= 2  # the inner pipeline's problems and the window's in one answer


def test_max_delay_zero_takes_nothing_at_or_before_the_newest_epoch():
    state = rsu_state_after(10, max_delay_s=0.0)
    batch = [first_rsu(9), first_rsu(8), *RSU_EPOCHS[10]]  # [0]: at the newest epoch itself
    fixes, new_state = RSU_IMU.process(state, batch, RSU_ENV)
    assert [f.t for f in fixes] == [RSU_EPOCHS[10][0].t]
    reasons = too_late_uses(fixes[0])
    assert set(reasons) == {0, 1}
    assert all("max_delay_s 0 s" in reason for reason in reasons.values())
    assert all(use.used for use in fixes[0].measurements if use.index > 1)
    reference, _ = feed(RSU_IMU, rsu_session(max_delay_s=0.0), RSU_EPOCHS[:11], RSU_ENV)
    assert current(new_state) == current(reference)
    # Nothing late is accepted, but the last batch stays so that the newest fix can be given again.
    assert lag._unpack(new_state).times == [RSU_EPOCHS[10][0].t]


@pytest.mark.parametrize(
    ("options", "batch_epochs", "stale"),
    # max_delay_s 0: the newest epoch itself is too late. max_window_epochs 2 with 5-epoch batches: the
    # window keeps the last 2 epochs of the batch (a checkpoint before them), so the epoch before is too late.
    [({"max_delay_s": 0.0}, 1, 9), ({"max_window_epochs": 2}, 5, 7)],
    ids=["max_delay_s 0", "max_window_epochs below a batch's epochs"],
)
def test_a_batch_of_only_too_late_measurements_is_answered_when_the_window_holds_no_epoch(
    options, batch_epochs, stale
):
    """A batch with nothing but too-late data must still carry its used=false report in the newest epoch's
    fix, as with a wide window: otherwise the client never learns its measurements were dropped. (The
    window holds no late-acceptable epoch with max_delay_s 0, or when one batch brings more epochs than
    max_window_epochs: it still keeps the newest epoch and a state before it.)"""
    batches = [
        [o for epoch in RSU_EPOCHS[k : k + batch_epochs] for o in epoch] for k in range(0, 10, batch_epochs)
    ]
    state, _ = feed(RSU_IMU, rsu_session(**options), batches, RSU_ENV)
    assert lag._unpack(state).times[-1] == RSU_EPOCHS[9][0].t
    fixes, new_state = RSU_IMU.process(state, [first_rsu(stale)], RSU_ENV)
    assert current(new_state) == current(state)
    assert len(fixes) == 1 and fixes[0].t == RSU_EPOCHS[9][0].t and fixes[0].revised
    assert set(too_late_uses(fixes[0])) == {0}
    assert_fix_close(fixes[0], RSU_REF_FIXES[fixes[0].t])


# -- 5. max_window_epochs ------------------------------------------------------------------------------
def test_the_window_keeps_at_most_max_window_epochs_and_older_data_is_too_late():
    state = rsu_session(max_window_epochs=5)
    for epoch in RSU_EPOCHS[:30]:
        _, state = RSU_IMU.process(state, epoch, RSU_ENV)
        assert len(lag._unpack(state).times) <= 5
    window = lag._unpack(state)
    newest = RSU_EPOCHS[29][0].t
    all_times = [epoch[0].t for epoch in RSU_EPOCHS]
    oldest = window.times[0]
    before = all_times[all_times.index(oldest) - 1]
    assert newest - before < MAX_DELAY_S  # within max_delay_s: only the epoch bound makes it too late
    fixes, after = RSU_IMU.process(state, [first_rsu(all_times.index(before))], RSU_ENV)
    reason = too_late_uses(fixes[-1])[0]
    assert "max_window_epochs 5" in reason
    assert current(after) == current(state)
    # The window's oldest epoch itself still takes late data.
    late = first_rsu(all_times.index(oldest))
    joined = [o for o in RSU_EPOCHS[all_times.index(oldest)] if o is not late]
    state = rsu_session(max_window_epochs=5)
    for k, epoch in enumerate(RSU_EPOCHS[:30]):
        _, state = RSU_IMU.process(state, joined if epoch[0].t == oldest else epoch, RSU_ENV)
    fixes, state = RSU_IMU.process(state, [late], RSU_ENV)
    assert not too_late_uses(fixes[-1]) and fixes[0].t == oldest and all(f.revised for f in fixes)
    assert_same_filter_state(state, rsu_state_after(30, max_window_epochs=5))


def test_late_data_after_one_epoch_batches_emptied_the_window_is_not_an_error():
    """max_window_epochs 2 with one-epoch batches: after three epochs since the last checkpoint the window
    moves its base to the current state and holds no epoch; a measurement within max_delay_s but at or
    before that base is too late (it raised IndexError while its report was written)."""
    state = rsu_session(max_window_epochs=2)
    for epoch in RSU_EPOCHS[:4]:
        _, state = RSU_IMU.process(state, epoch, RSU_ENV)
    window = lag._unpack(state)
    assert window.times == [] and window.base.t == RSU_EPOCHS[3][0].t
    _, after = RSU_IMU.process(state, [first_rsu(3)], RSU_ENV)
    assert current(after) == current(state)


# -- 6. the state format ---------------------------------------------------------------------------------
def sample_observations() -> list[Observation]:
    return [
        RsuObservation(1.5, "S+000", 12.25, -3.0),
        GyroObservation(1.5, 0.0125),
        RsuRangeObservation(1.5, "N-250", 99.5),
        GnssFixObservation(1.5, 3.0, -4.0),
        GnssFixObservation(1.5, 3.0, -4.0, 2.5),
        OdometerObservation(1.5, distance=0.75),
        OdometerObservation(1.5, speed=15.0),
        V2vRangeObservation(1.5, "north", range=33.0),
        V2vRangeObservation(1.5, "north", toa=1.1e-7),
        PseudorangeObservation(1.5, "G", 7, 2.1e7, 44.5),
        PseudorangeObservation(1.5, "C", 30, 2.4e7, 39.0, (-1.2e7, 1.5e7, 2.1e7), 1.2e-5),
        PseudorangeObservation(1.5, "E", 3, 2.3e7, 41.0, (1.0, 2.0, 3.0), None),
        PseudorangeObservation(1.5, "E", 5, 2.3e7, 41.0, None, None, -2345.25),
        RissObservation(1.5, 14.0, 0.3, -0.1, 0.02),
    ]


def test_every_observation_kind_round_trips_through_the_record_codec():
    observations = sample_observations()
    assert {type(o) for o in observations} == set(typing.get_args(Observation))  # a new kind needs a sample
    decoded = lag.decode_epoch(lag.encode_epoch(observations))
    assert decoded == observations
    assert [type(o) for o in decoded] == [type(o) for o in observations]
    assert isinstance(decoded[10].sat_position, tuple) and decoded[9].sat_position is None


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=4, max_size=4), st.text(max_size=8)
)
def test_numbers_and_ids_round_trip_bit_for_bit(numbers, rsu_id):
    t, r, b, w = numbers
    observations = [RsuObservation(t, rsu_id, r, b), GyroObservation(t, w)]
    decoded = lag.decode_epoch(lag.encode_epoch(observations))
    assert decoded == observations
    assert [math.copysign(1.0, v) for v in (decoded[0].t, decoded[0].range)] == [
        math.copysign(1.0, v) for v in (t, r)
    ]


@pytest.mark.parametrize(
    "record",
    [
        b'[["nope", 1.0]]',
        b"not json",
        b"[[]]",
        b'{"kind": "gyro"}',
        b"[1]",
        b'[["gyro", 1.0]]',
        b'[["gyro", 1.0, 2.0, 3.0]]',
        b'[["rsu", 1.0, "S+000", 1.0, 2.0], ["teleport", 1.0]]',
    ],
)
def test_an_undecodable_record_is_a_state_format_error(record):
    with pytest.raises(StateFormatError):
        lag.decode_epoch(record)


def test_the_window_round_trips_through_its_bytes():
    records = [lag.encode_epoch(RSU_EPOCHS[k]) for k in range(3)]
    window = lag._Window(
        {"max_delay_s": 0.75, "max_window_epochs": 17, "max_lead_s": 12.5},
        RSU_EPOCHS[2][0].t,
        [lag._Checkpoint(None, b"base state"), lag._Checkpoint(RSU_EPOCHS[0][0].t, b"\x00\x01 checkpoint")],
        b"current \xff",
        [RSU_EPOCHS[k][0].t for k in range(3)],
        records,
    )
    assert lag._unpack(lag._pack(window)) == window
    empty = lag._Window(dict(lag.DEFAULTS), None, [lag._Checkpoint(None, b"")], b"", [], [])
    assert lag._unpack(lag._pack(empty)) == empty
    for state in (RSU_REF_STATE, rsu_session()):
        assert lag._pack(lag._unpack(state)) == state


def test_a_version_2_window_is_converted_when_read():
    """Windows stored before doppler_hz (version 2) keep working: their pseudorange records are read in the
    old layout and rewritten in the new one; the session's observations come back without Doppler."""
    from edgepos.core.observation_codec import _KindCodec
    from edgepos.core.observations import PseudorangeObservationV2

    old_codec = _KindCodec(PseudorangeObservationV2)
    old = [
        PseudorangeObservationV2(1.5, "G", 7, 2.1e7, 44.5),
        PseudorangeObservationV2(1.5, "E", 3, 2.3e7, 41.0),
    ]
    gyro = [GyroObservation(2.5, 0.125)]
    window = lag._Window(
        dict(lag.DEFAULTS),
        2.5,
        [lag._Checkpoint(None, b"base")],
        b"current",
        [1.5, 2.5],
        [b"".join(old_codec.encode(o) for o in old), lag.encode_epoch(gyro)],
    )
    packed = lag._pack(window)
    version_2 = packed[:4] + bytes([2]) + packed[5:]
    converted = lag._unpack(version_2)
    assert converted.observations() == [o.current() for o in old] + gyro
    assert lag._pack(converted)[4] == lag.VERSION == 3
    with pytest.raises(StateFormatError, match="version 1"):
        lag._unpack(packed[:4] + bytes([1]) + packed[5:])


def test_damaged_window_bytes_are_state_format_errors():
    state = rsu_state_after(3)
    header = lag_state._HEADER.size
    edges = (0, 3, 4, 5, header - 1, header, header + 1, len(state) - 13, len(state) - 1)
    cuts = {*edges, *range(0, len(state), 211)}
    for cut in sorted(cuts):
        with pytest.raises(StateFormatError):
            lag._unpack(state[:cut])
    with pytest.raises(StateFormatError):
        lag._unpack(b"EPLX" + state[4:])
    with pytest.raises(StateFormatError):
        lag._unpack(state[:4] + bytes([lag.VERSION + 1]) + state[5:])
    with pytest.raises(StateFormatError):
        lag._unpack(state + b"\x00")
    with pytest.raises(StateFormatError):
        RSU_IMU.process(state[:-1], RSU_EPOCHS[3], RSU_ENV)


# -- 6b. the in-order path (``LagWindow._in_order``) against the general one ------------------------------
def feed_both(
    batches: Sequence[Sequence[Observation]],
    state: bytes,
    monkeypatch: pytest.MonkeyPatch,
    env: Environment = RSU_ENV,
    pipeline: Pipeline = RSU_IMU,
) -> tuple[bytes, list[list[Fix]]]:
    """``batches`` sent with the in-order path and without it, asserting after every batch the same fixes
    and the same state bytes (or the same problems); the state and responses of the first."""
    fast_state, slow_state = state, state
    responses = []
    for batch in batches:
        outcomes = []
        for enabled, before in ((True, fast_state), (False, slow_state)):
            monkeypatch.setattr(lag, "IN_ORDER_PATH", enabled)
            try:
                outcomes.append(pipeline.process(before, list(batch), env))
            except PipelineInputError as error:
                outcomes.append(error.problems)
        assert outcomes[0] == outcomes[1]
        if isinstance(outcomes[0], tuple):
            (fixes, fast_state), (_, slow_state) = outcomes
            responses.append(fixes)
    monkeypatch.setattr(lag, "IN_ORDER_PATH", True)
    assert fast_state == slow_state
    return fast_state, responses


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    delays=st.dictionaries(st.integers(0, len(RSU_OBSERVATIONS) - 1), st.floats(0.0, 1.2), max_size=20),
    batch_epochs=st.integers(1, 6),
    max_window_epochs=st.sampled_from([2, 5, 200]),
    max_delay_s=st.sampled_from([0.0, 0.3, 1.0]),
    shuffle=st.booleans(),
)
@example(delays={}, batch_epochs=1, max_window_epochs=200, max_delay_s=1.0, shuffle=False)
@example(delays={}, batch_epochs=6, max_window_epochs=2, max_delay_s=1.0, shuffle=False)
@example(delays={30: 0.4}, batch_epochs=1, max_window_epochs=5, max_delay_s=1.0, shuffle=False)
def test_the_in_order_path_gives_the_general_paths_fixes_and_bytes(
    delays, batch_epochs, max_window_epochs, max_delay_s, shuffle
):
    """Whatever the arrival (in order, late, too late, shuffled within a batch, more epochs than the window
    keeps), every batch answers the same fixes and leaves the same state bytes with the in-order path as
    without it: the path only skips decoding, never changes what is kept."""
    arrivals = np.array([o.t for o in RSU_OBSERVATIONS])
    for index, delay in delays.items():
        arrivals[index] += delay
    batches = arrival_batches(RSU_OBSERVATIONS, arrivals, batch_epochs)
    if shuffle:
        for batch in batches:
            random.Random(len(batch)).shuffle(batch)
    options = {"max_window_epochs": max_window_epochs, "max_delay_s": max_delay_s}
    with pytest.MonkeyPatch.context() as monkeypatch:
        feed_both(batches, rsu_session(**options), monkeypatch)


@pytest.mark.parametrize(
    "odd_t",
    [
        lambda t: int(t) + 1,  # an int after the window: accepted as a number
        lambda t: True,  # a bool: refused, as a number it is not
        lambda t: math.nan,
        lambda t: math.inf,
        lambda t: t,  # a duplicate of its epoch's time, as an int when it is whole
    ],
)
def test_batches_with_times_the_in_order_path_leaves_alone_answer_as_the_general_path(odd_t, monkeypatch):
    """The in-order path tests a batch's times as a whole (floats, finite, in order): a batch with an int,
    a bool, NaN or an infinity among them goes to the general path, with the same answer either way."""
    batches = [[o for e in RSU_EPOCHS[k : k + 5] for o in e] for k in range(0, 20, 5)]
    last = batches[-1]
    last[-1] = dataclasses.replace(last[-1], t=odd_t(last[-1].t))
    whole = [dataclasses.replace(o, t=float(round(o.t))) for o in RSU_EPOCHS[20]]
    feed_both(
        [*batches, whole, [dataclasses.replace(whole[0], t=int(whole[0].t))]], rsu_session(), monkeypatch
    )


def test_an_in_order_batch_after_a_late_one_still_replays_correctly(monkeypatch):
    """Late data, then batches in time order (the in-order path), then late data again reaching back
    before them: the result is time order's, and the in-order batches never decoded the window."""
    late, later = first_rsu(12), first_rsu(27)
    without = [[o for o in epoch if o is not late and o is not later] for epoch in RSU_EPOCHS[:30]]
    batches = [
        *without[:16],
        [late],  # 0.2 s late: filtered again from a checkpoint
        *without[16:30],  # in order again
        [later],  # joins an epoch the in-order path stored: its record is decoded and replaced
    ]
    state, responses = feed_both(batches, rsu_session(), monkeypatch)
    reference, reference_responses = feed(RSU_IMU, rsu_session(), RSU_EPOCHS[:30], RSU_ENV)
    assert_same_filter_state(state, reference)
    latest, want = last_fixes(responses), last_fixes(reference_responses)
    assert latest.keys() == want.keys()
    for t, fix in latest.items():
        assert_fix_close(fix, want[t])
    assert responses[-1][0].t == RSU_EPOCHS[27][0].t and all(f.revised for f in responses[-1])

    def no_decoding(_state: bytes) -> None:
        raise AssertionError("an in-order batch decoded the whole window")

    monkeypatch.setattr(lag, "_unpack", no_decoding)
    fixes, after = RSU_IMU.process(state, RSU_EPOCHS[30], RSU_ENV)
    assert [f.t for f in fixes] == [RSU_EPOCHS[30][0].t] and not fixes[0].revised
    monkeypatch.undo()
    assert lag._unpack(after).newest == RSU_EPOCHS[30][0].t


@pytest.mark.parametrize("batch_epochs", [1, 3])
@pytest.mark.parametrize("name", ["v2v_coop", "v2x_federated", "gnss_tight"])
def test_the_in_order_path_gives_the_same_bytes_for_the_other_pipelines(
    name, batch_epochs, v2v_data, v2x_data, gnss_data, monkeypatch
):
    """The other pipelines' windows too (their own records and states): batches in time order, then the
    late ones of a schedule, the same fixes and bytes with the in-order path as without it."""
    epochs, env = {"v2v_coop": v2v_data, "v2x_federated": v2x_data, "gnss_tight": gnss_data}[name]
    options = {
        "v2v_coop": {"method": "aug_ukf"},
        "v2x_federated": {},
        "gnss_tight": {
            "filter": "pf",
            "particles": 100,
            "seed": 3,
            "systems": ["C", "G"],
            "max_delay_s": 5.0,
        },
    }[name]
    pipeline = get_pipeline(name)
    in_order = [
        [o for e in epochs[k : k + batch_epochs] for o in e] for k in range(0, len(epochs), batch_epochs)
    ]
    late = scheduled(epochs, SCHEDULES["several late, delivered newest first"])
    for batches in (in_order, late):
        feed_both(batches, new_session(pipeline, options), monkeypatch, env, pipeline)


def test_the_in_order_path_leaves_older_windows_and_damage_to_the_general_path():
    """A version-2 window (converted when read) and damaged bytes do not take the in-order path."""
    state = rsu_state_after(5)
    assert lag_state._spans(state) is not None
    assert lag_state._spans(state[:4] + bytes([2]) + state[5:]) is None
    for cut in (len(state) - 1, lag_state._HEADER.size + 3, 3):
        assert lag_state._spans(state[:cut]) is None
    assert lag_state._spans(state + b"\x00") is None


# -- 7. bounded size ---------------------------------------------------------------------------------------
def test_the_state_stays_bounded_over_a_long_in_order_run():
    period = SCENARIO.period
    steps = 2000
    truth = build_trajectory(
        (Cruise(period * (steps + 1)),), start=(0.0, 0.0), heading0=0.0, speed0=10.0, period=period
    )
    scenario = dataclasses.replace(
        SCENARIO, name="long cruise", truth=truth, rsus=staggered_rsus(-300.0, 1400.0)
    )
    epochs = rsu_imu_epochs(scenario, np.random.default_rng([SEED, 1]))[:steps]
    assert len(epochs) == steps
    env = environment(scenario)
    state = new_session(RSU_IMU, None, initial_state(scenario))
    largest = inner_largest = 0
    for epoch in epochs:
        _, state = RSU_IMU.process(state, epoch, env)
        window = lag._unpack(state)
        inner_largest = max(inner_largest, len(window.current), *(len(c.state) for c in window.checkpoints))
        largest = max(largest, len(state))
    # The bound: at most CHECKPOINTS_PER_WINDOW checkpoints in max_delay_s (spaced by max_delay_s /
    # CHECKPOINTS_PER_WINDOW), one more at the window's start and the base before it; the current state;
    # and the epochs since the base (max_delay_s plus a checkpoint spacing plus one batch), each with
    # its record and 12 bytes of index.
    delay = MAX_DELAY_S
    spacing = delay / lag.CHECKPOINTS_PER_WINDOW
    checkpoints = lag.CHECKPOINTS_PER_WINDOW + 2
    epochs_kept = math.ceil((delay + spacing + period) / period) + 1
    record = max(len(lag.encode_epoch(epoch)) for epoch in epochs)
    bound = (
        lag_state._HEADER.size
        + checkpoints * (lag_state._CHECKPOINT.size + inner_largest)
        + inner_largest
        + epochs_kept * (12 + record)
    )
    assert largest < bound, (largest, bound)
    window = lag._unpack(state)
    assert len(window.checkpoints) <= checkpoints
    assert window.newest - window.times[0] >= delay - 1e-9  # the window really keeps max_delay_s


# -- 8. track() -----------------------------------------------------------------------------------------------
def test_track_is_the_fixes_served_for_the_window_epochs():
    window = lag._unpack(RSU_REF_STATE)
    track = RSU_IMU.track(RSU_REF_STATE, RSU_ENV, smoothed=False)
    assert [fix.t for fix in track] == window.times and len(window.times) >= MAX_DELAY_S / SCENARIO.period
    for fix in track:
        assert_fix_close(fix, RSU_REF_FIXES[fix.t])
        assert fix.measurements == []
    assert RSU_IMU.track(rsu_session(), RSU_ENV, smoothed=False) == []


@pytest.mark.skipif(
    not RSU_IMU.smoother, reason="the rsu_imu smoother (RsuImuPipeline.smooth) is not there yet"
)
def test_smoothed_track_has_the_same_epochs_and_finite_values():
    window = lag._unpack(RSU_REF_STATE)
    track = RSU_IMU.track(RSU_REF_STATE, RSU_ENV, smoothed=True)
    assert [fix.t for fix in track] == window.times
    for fix in track:
        assert all(math.isfinite(getattr(fix, name)) for name in ("x", "y", "vx", "vy"))


def test_smoothing_a_pipeline_without_a_smoother_is_a_value_error():
    pipeline = get_pipeline("v2x_federated")
    assert not pipeline.smoother
    run = federated_run(3, 0, "clean", steps=3)
    state, _ = feed(pipeline, new_session(pipeline), run.observations, StaticEnvironment())
    with pytest.raises(ValueError, match="no smoother"):
        pipeline.track(state, StaticEnvironment(), smoothed=True)


def test_replayed_observations_name_what_a_late_batch_filters_again():
    """In time order nothing is filtered again (answered from the header alone); a late measurement
    brings back the stored observations from the checkpoint before it; None asks for the whole window."""
    state = rsu_state_after(10)
    assert RSU_IMU.replayed_observations(state, RSU_EPOCHS[10]) == []
    late = [*RSU_EPOCHS[10], first_rsu(7)]
    replayed = RSU_IMU.replayed_observations(state, late)
    assert replayed and min(o.t for o in replayed) <= first_rsu(7).t
    assert all(o in [x for epoch in RSU_EPOCHS[:10] for x in epoch] for o in replayed)
    assert RSU_IMU.replayed_observations(state, None) == lag._unpack(state).observations()
    nan_time = dataclasses.replace(RSU_EPOCHS[10][0], t=math.nan)
    assert RSU_IMU.replayed_observations(state, [nan_time]) == []  # not late: the inner pipeline refuses it
    assert lag_state.newest_epoch(state) == RSU_EPOCHS[9][0].t
    assert lag_state.newest_epoch(rsu_session()) is None


@given(st.lists(st.integers(1, 4), max_size=8), st.randoms(use_true_random=False))
def test_a_batchs_records_are_each_epochs_encoding(counts, rng):
    """``lag_state.encode_epochs`` (the in-order path's records from one pass) gives each epoch's
    ``encode_epoch``, for epochs of one to four observations of mixed kinds."""
    observations: list[Observation] = []
    epochs = []
    for k, count in enumerate(counts):
        epoch: list[Observation] = [
            RsuObservation(0.1 * k, f"R{rng.randrange(3)}", rng.uniform(0, 90), 0.1)
            if rng.random() < 0.7
            else GyroObservation(0.1 * k, rng.uniform(-1, 1))
            for _ in range(count)
        ]
        epochs.append(epoch)
        observations += epoch
    assert lag_state.encode_epochs(observations, counts) == [lag_state.encode_epoch(e) for e in epochs]
