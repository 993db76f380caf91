"""The CPU cost model of a batch (``edgepos.pipelines.cost``) held to measured time, and its shape.

Measured against predicted: for a few representative configurations per pipeline, ``process`` is run
on a realistic batch (after a warm-up call, so no numba compilation or first-call cache is timed) and
its thread CPU time (median of five runs) compared with the prediction:

* measured <= TOLERANCE x predicted: the model is an upper bound. It is calibrated on this box with a
  margin over the upper envelope of the measurements (``bench/batch_cost.py``); TOLERANCE = 3 leaves room
  for a CI runner that is slower or whose CPU is shared with other jobs (thread CPU time excludes time
  spent waiting, but contention for caches and cores still inflates it: the same batch was seen to take
  up to 2.35x as long between two runs on a loaded box), and still fails a model that misses a feature
  (an order of magnitude off).
* predicted <= RATIO x measured: the model is not absurdly conservative (a bound ten times the real
  cost would refuse reasonable batches). RATIO = 6: the envelope covers the most expensive shape of
  each feature (the PF at its most likelihood stages, the first epochs of a session), measured under
  load, plus the margin.

The whole module takes a few seconds.
"""

from __future__ import annotations

import dataclasses
import itertools
import statistics
import time
from pathlib import Path

import numpy as np
import pytest
from edgepos.core.compiled import warm_up
from edgepos.core.observations import GyroObservation, PseudorangeObservation, V2vRangeObservation
from edgepos.pipelines import cost, tracks
from edgepos.pipelines.base import InitialState, NeighbourTrack, StaticEnvironment
from edgepos.pipelines.registry import PIPELINES, get_pipeline

TOLERANCE = 3.0
RATIO = 6.0
REPS = 5
GNSS_DATA = Path(__file__).resolve().parents[1] / "data" / "gnss-rover"


def cpu_seconds(pipeline_name: str, state: bytes, batch: list, environment) -> float:
    """Median thread CPU seconds of ``process`` over REPS runs, after one warm-up run."""
    pipeline = get_pipeline(pipeline_name)
    pipeline.process(state, batch, environment)
    times = []
    for _ in range(REPS):
        started = time.thread_time()
        pipeline.process(state, batch, environment)
        times.append(time.thread_time() - started)
    return statistics.median(times)


def advance(pipeline_name: str, state: bytes, epochs, environment) -> bytes:
    pipeline = get_pipeline(pipeline_name)
    for epoch in epochs:
        _, state = pipeline.process(state, list(epoch), environment)
    return state


# -- workloads -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rsu_imu_workload():
    from edgepos.sim.scenarios import rsu_imu_paper_scenario
    from edgepos.sim.sensors import environment, rsu_imu_epochs

    warm_up()
    scenario = rsu_imu_paper_scenario()
    rng = np.random.default_rng(3)
    epochs = rsu_imu_epochs(scenario, rng)
    jitter = rng.uniform(-0.003, 0.003, len(epochs))  # real clocks: no interval's F and Q from a cache
    epochs = [[dataclasses.replace(o, t=o.t + float(j)) for o in e] for e, j in zip(epochs, jitter)]
    x0 = scenario.initial_state
    return epochs, environment(scenario), InitialState(x0[0], x0[3], x0[1], x0[4])


@pytest.fixture(scope="module")
def gnss_workload():
    from edgepos.gnss.ephemerides import Ephemerides
    from edgepos.gnss.rinex_nav import read_navigation
    from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
    from edgepos.pipelines.gnss_recording import epoch_pseudoranges

    codes = {s: DEFAULT_CODES[s] for s in "GCE"}
    navigation = Ephemerides.from_navigation(read_navigation(str(GNSS_DATA / "broadcast-nav.rnx")))
    epochs = []
    for number, epoch in enumerate(read_epochs(str(GNSS_DATA / "rover-0-5min.rnx"), codes)):
        if number >= 16:
            break
        epochs.append(epoch_pseudoranges(epoch, carrier=False))
    return epochs, StaticEnvironment(navigation=navigation)


def _without_doppler(epoch: list[PseudorangeObservation]) -> list[PseudorangeObservation]:
    return [dataclasses.replace(o, doppler_hz=None) for o in epoch]


def _with_repeats(epoch: list[PseudorangeObservation], count: int) -> list[PseudorangeObservation]:
    """The epoch's pseudoranges, repeated (centimetres apart) up to ``count``, as a client may send."""
    out = list(epoch[:count])
    k = 0
    while len(out) < count:
        o = epoch[k % len(epoch)]
        out.append(dataclasses.replace(o, pseudorange=o.pseudorange + 0.05 * (k + 1)))
        k += 1
    return out


def _check(pipeline_name: str, options: dict, state: bytes, batch: list, environment) -> tuple[float, float]:
    resolved = get_pipeline(pipeline_name).resolve_options(options)
    predicted = cost.batch_cost_s(pipeline_name, resolved, batch)
    measured = cpu_seconds(pipeline_name, state, batch, environment)
    label = f"{pipeline_name} {options}: measured {1e3 * measured:.2f} ms, predicted {1e3 * predicted:.2f} ms"
    assert measured <= TOLERANCE * predicted, label
    assert predicted <= RATIO * measured, label
    return measured, predicted


# -- measured against predicted ------------------------------------------------------------------
@pytest.mark.parametrize(
    "options, epochs",
    [
        ({}, 20),  # the paper's 2IMM-CKF, compiled
        ({"integrity": True}, 20),  # the same with the integrity monitor's bank of sub-filters
        ({"filter": "ekf", "models": ["ca"], "priority": [], "rsu_handling": "average"}, 20),
        (  # the current-statistical model: the numpy reference
            {
                "filter": "ukf",
                "models": ["cv", "ca", "ct", "at", "singer", "current_statistical"],
                "rsu_handling": "average",
            },
            5,
        ),
    ],
)
def test_rsu_imu_measured_within_the_model(rsu_imu_workload, options, epochs) -> None:
    observations, environment, initial = rsu_imu_workload
    pipeline = get_pipeline("rsu_imu")
    state = pipeline.create(pipeline.resolve_options(options), initial)
    state = advance("rsu_imu", state, [[o for e in observations[:60] for o in e]], environment)
    batch = [o for e in observations[60 : 60 + epochs] for o in e]
    _check("rsu_imu", options, state, batch, environment)


@pytest.mark.parametrize(
    "options, pseudoranges, epochs, doppler",
    [
        ({"filter": "ukf", "seed": 1}, 22, 3, False),
        ({"filter": "upf", "particles": 200, "seed": 1}, 22, 1, False),
        ({"filter": "upf", "particles": 100, "seed": 1}, 40, 1, False),
        ({"filter": "pf", "particles": 500, "seed": 1}, 22, 1, False),
        # With Doppler every pseudorange adds a range-rate row to the update; the constants were fitted
        # without (measured/predicted for the UPF rose from about 1.1 to 1.3 on a loaded box: within
        # TOLERANCE, but the model wants a refit with Doppler cases in bench/batch_cost.py).
        ({"filter": "ukf", "seed": 1}, 22, 3, True),
        ({"filter": "upf", "particles": 200, "seed": 1}, 22, 1, True),
        ({"filter": "upf", "particles": 100, "seed": 1}, 40, 1, True),
        ({"filter": "pf", "particles": 500, "seed": 1}, 22, 1, True),
    ],
)
def test_gnss_tight_measured_within_the_model(gnss_workload, options, pseudoranges, epochs, doppler) -> None:
    observations, environment = gnss_workload
    if not doppler:
        observations = [_without_doppler(e) for e in observations]
    pipeline = get_pipeline("gnss_tight")
    state = pipeline.create(pipeline.resolve_options(options), None)
    state = advance("gnss_tight", state, observations[:10], environment)
    batch = [o for e in observations[10 : 10 + epochs] for o in _with_repeats(e, pseudoranges)]
    _check("gnss_tight", options, state, batch, environment)


@pytest.fixture(scope="module")
def v2v_workload():
    from edgepos.sim.v2v import VEHICLE_IDS, make_run

    run = make_run(1, 0, "straight")
    return run, VEHICLE_IDS


@pytest.mark.parametrize("method", ["gps", "gps_dr", "aug_ukf"])
def test_v2v_coop_measured_within_the_model(v2v_workload, method) -> None:
    run, ids = v2v_workload
    pipeline = get_pipeline("v2v_coop")
    options = {"method": method}
    resolved = pipeline.resolve_options(options)
    states = {vid: pipeline.create(resolved, None) for vid in ids}
    published: dict[str, NeighbourTrack] = {}
    end = 45
    for k in range(end):
        snapshot = dict(published)
        for i, vid in enumerate(ids):
            fixes, states[vid] = pipeline.process(
                states[vid], run.observations[i][k], StaticEnvironment(tracks=snapshot, vehicle_id=vid)
            )
            track = tracks.publish(vid, published.get(vid), fixes, keep=1000)
            if track is not None:
                published[vid] = track
    start = 30  # ego: replay epochs 30..44 against its neighbours' whole tracks (every range usable)
    ego = StaticEnvironment(tracks=published, vehicle_id=ids[0])
    state = pipeline.create(resolved, None)
    state = advance("v2v_coop", state, run.observations[0][:start], ego)
    batch = [o for k in range(start, end) for o in run.observations[0][k]]
    assert any(isinstance(o, V2vRangeObservation) for o in batch)
    _check("v2v_coop", options, state, batch, ego)


@pytest.mark.parametrize("feedback", [True, False])
def test_v2x_federated_measured_within_the_model(feedback) -> None:
    from edgepos.eval.federated import assisting_tracks
    from edgepos.sim.federated import make_run

    run = make_run(1, 0, "clean", steps=40)
    neighbours = assisting_tracks(run)
    pipeline = get_pipeline("v2x_federated")
    options = {"feedback": feedback}
    state = pipeline.create(pipeline.resolve_options(options), None)
    for k in range(30):
        _, state = pipeline.process(
            state, run.observations[k], StaticEnvironment(tracks=neighbours[k], vehicle_id="target")
        )
    # The evaluation feeds one epoch at a time; here a 4-epoch batch against the tracks before it.
    environment = StaticEnvironment(tracks=neighbours[29], vehicle_id="target")
    batch = [o for k in range(30, 34) for o in run.observations[k]]
    _check("v2x_federated", options, state, batch, environment)


# -- the model's shape ---------------------------------------------------------------------------
def test_every_registered_pipeline_has_a_calibrated_model() -> None:
    for name in PIPELINES:
        model = cost.cost_model(name)
        assert set(model.features) <= set(cost.CALIBRATION[name]), name
        assert all(value >= 0.0 for value in cost.CALIBRATION[name].values()), name
        assert name in cost.MAX_PER_EPOCH
        assert cost.epoch_cost_s(name, None) > 0.0
    with pytest.raises(KeyError):
        cost.cost_model("no_such_pipeline")


def test_a_pipeline_without_a_model_fails_the_import_check(monkeypatch) -> None:
    monkeypatch.setitem(cost.PIPELINES, "brand_new", PIPELINES["rsu_imu"])
    with pytest.raises(RuntimeError, match="brand_new"):
        cost._check_registry()


def test_a_feature_without_a_constant_fails_the_import_check(monkeypatch) -> None:
    trimmed = dict(cost.CALIBRATION["v2v_coop"])
    trimmed.pop("aug_ukf.range")
    monkeypatch.setattr(cost.cost_model("v2v_coop"), "coefficients", trimmed)
    with pytest.raises(RuntimeError, match="aug_ukf.range"):
        cost._check_registry()


def _pseudorange_epochs(epochs: int, per_epoch: int) -> list[PseudorangeObservation]:
    return [
        PseudorangeObservation(100.0 + k, "G", 1 + j % 32, 2.2e7 + j, 45.0)
        for k in range(epochs)
        for j in range(per_epoch)
    ]


def test_cost_grows_with_epochs_particles_and_pseudoranges() -> None:
    for name in ("ukf", "pf", "upf"):
        options = {"filter": name, "particles": 200}
        by_epochs = [
            cost.batch_cost_s("gnss_tight", options, _pseudorange_epochs(e, 20)) for e in (1, 2, 5, 20)
        ]
        assert by_epochs == sorted(by_epochs) and by_epochs[0] < by_epochs[-1], name
        by_prs = [cost.epoch_cost_s("gnss_tight", options, {"pseudorange": m}) for m in (0, 6, 15, 22, 40)]
        assert by_prs == sorted(by_prs) and by_prs[0] < by_prs[-1], name
    for name in ("pf", "upf"):
        by_particles = [
            cost.epoch_cost_s("gnss_tight", {"filter": name, "particles": n})
            for n in (10, 50, 200, 1000, 5000)
        ]
        assert all(a < b for a, b in itertools.pairwise(by_particles)), name
    # The UKF ignores the particles option.
    assert cost.epoch_cost_s("gnss_tight", {"filter": "ukf", "particles": 10}) == cost.epoch_cost_s(
        "gnss_tight", {"filter": "ukf", "particles": 5000}
    )


def _non_decreasing(values: list[float]) -> bool:
    return all(a <= b for a, b in itertools.pairwise(values))


def test_rsu_imu_cost_grows_with_models_and_used_rsus_only() -> None:
    """Never less for more models or more RSUs used; RSUs beyond max_rsus add only their bookkeeping.
    (Non-decreasing rather than growing: the envelope may be flat in a feature whose cost the other
    features' constants already cover over the accepted range. So it is for the models of a compiled
    averaged bank, where the grid's one-model bank costs more than its larger ones (pipelines/cost.py);
    every other path grows with its models.)"""
    models = ["cv", "ca", "ct", "at", "singer", "current_statistical"]
    per_observation = cost.MARGIN * cost.CALIBRATION["rsu_imu"]["observation"]
    for filter_name in ("ekf", "ukf", "ckf", "srukf"):
        for handling in ("joint", "average"):
            by_models = [
                cost.epoch_cost_s(
                    "rsu_imu",
                    {"filter": filter_name, "models": models[:m], "priority": [], "rsu_handling": handling},
                )
                for m in range(1, 6)  # cv..singer: all compiled (srukf: all reference)
            ]
            assert _non_decreasing(by_models), (filter_name, handling)
            if not (handling == "average" and filter_name != "srukf"):
                assert by_models[0] < by_models[-1], (filter_name, handling)
            options = {"filter": filter_name, "rsu_handling": handling, "max_rsus": 8}
            by_rsus = [
                cost.epoch_cost_s("rsu_imu", options, {"rsu": k, "gyro": 1}) for k in (0, 1, 4, 8, 16, 64)
            ]
            assert _non_decreasing(by_rsus) and by_rsus[0] < by_rsus[3], (filter_name, handling)
            assert by_rsus[5] - by_rsus[3] == pytest.approx(56 * per_observation)
    compiled = cost.epoch_cost_s("rsu_imu", {"models": models[:5]})
    reference = cost.epoch_cost_s("rsu_imu", {"models": models})
    assert reference > 2.0 * compiled  # the current-statistical model takes the bank off the kernels


def test_reference_path_when_numba_is_off(monkeypatch) -> None:
    before = cost.epoch_cost_s("rsu_imu", {})
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    assert cost.epoch_cost_s("rsu_imu", {}) > 2.0 * before


def test_cooperative_cost_never_falls_with_more_ranges() -> None:
    for method in ("gps", "gps_dr", "ukf", "aug_ukf"):
        by_ranges = [
            cost.epoch_cost_s("v2v_coop", {"method": method}, {"gnss_fix": 1, "v2v_range": r})
            for r in (0, 1, 8, 32)
        ]
        assert _non_decreasing(by_ranges), method
    aug = [
        cost.epoch_cost_s("v2v_coop", {"method": "aug_ukf"}, {"gnss_fix": 1, "v2v_range": r}) for r in (0, 32)
    ]
    assert aug[0] < aug[1]
    by_ranges = [
        cost.epoch_cost_s("v2x_federated", {}, {"gnss_fix": 1, "rsu_range": r, "v2v_range": r})
        for r in (0, 1, 8, 32)
    ]
    assert _non_decreasing(by_ranges) and by_ranges[0] < by_ranges[-1]


def test_defaults_fit_the_default_budget_at_the_largest_epoch() -> None:
    """A session with default options passes the session-creation check."""
    for name in PIPELINES:
        assert cost.epoch_cost_s(name, None) <= cost.DEFAULT_BUDGET_S, name
        assert cost.budget_fits(name, None)


def test_max_particles_is_the_largest_that_fits() -> None:
    for name in ("pf", "upf"):
        most = cost.max_particles(name)
        assert most >= 10, name
        largest = {
            "pseudorange": cost.MAX_PER_EPOCH["gnss_tight"]["pseudorange"],
            "riss": cost.MAX_PER_EPOCH["gnss_tight"]["riss"],
        }
        assert (
            cost.epoch_cost_s("gnss_tight", {"filter": name, "particles": most}, largest)
            <= cost.DEFAULT_BUDGET_S
        )
        assert (
            cost.epoch_cost_s("gnss_tight", {"filter": name, "particles": most + 1}, largest)
            > cost.DEFAULT_BUDGET_S
        )
        assert cost.max_particles(name, budget_s=2 * cost.DEFAULT_BUDGET_S) > most


def test_epoch_bounds_name_the_epoch_and_kind() -> None:
    bound = cost.MAX_PER_EPOCH["gnss_tight"]["pseudorange"]
    within = _pseudorange_epochs(3, bound)
    assert cost.epoch_bound_violations("gnss_tight", within) == []
    over = within + [PseudorangeObservation(101.0, "C", 7, 2.3e7, 40.0)]
    (violation,) = cost.epoch_bound_violations("gnss_tight", over)
    assert (violation.t, violation.kind, violation.count, violation.bound) == (
        101.0,
        "pseudorange",
        bound + 1,
        bound,
    )
    assert "pseudorange" in violation.reason and str(bound) in violation.reason
    gyros = [GyroObservation(5.0, 0.01)] * (cost.MAX_PER_EPOCH["rsu_imu"]["gyro"] + 1)
    assert [v.kind for v in cost.epoch_bound_violations("rsu_imu", gyros)] == ["gyro"]


def test_epoch_counts_group_by_time_and_every_route_agrees() -> None:
    """batch_cost_s, batch_cost_from_counts_s and the calibrated sum of batch_features (what the bench
    fits) give the same prediction."""
    batch = _pseudorange_epochs(2, 3) + [GyroObservation(100.0, 0.0)]
    assert cost.epoch_counts(batch) == [{"pseudorange": 3, "gyro": 1}, {"pseudorange": 3}]
    mixed = _pseudorange_epochs(5, 7) + [
        dataclasses.replace(o, system="C") for o in _pseudorange_epochs(3, 2)
    ]
    for name, options in (("gnss_tight", None), ("gnss_tight", {"filter": "pf", "particles": 300})):
        direct = cost.batch_cost_s(name, options, mixed)
        assert cost.batch_cost_from_counts_s(name, options, cost.epoch_counts(mixed)) == pytest.approx(direct)
        features = cost.batch_features(name, options, cost.epoch_counts(mixed))
        weighed = cost.MARGIN * sum(cost.CALIBRATION[name][f] * v for f, v in features.items())
        assert weighed == pytest.approx(direct)


def test_admission_in_one_pass_agrees_with_the_two_functions() -> None:
    """What the service computes per batch (``admit``) is exactly the cost and the bound violations."""
    batch = _pseudorange_epochs(3, 41)
    options = get_pipeline("gnss_tight").resolve_options({"filter": "upf"})
    predicted, violations = cost.admit("gnss_tight", options, batch)
    assert predicted == cost.batch_cost_s("gnss_tight", options, batch)
    assert violations == cost.epoch_bound_violations("gnss_tight", batch)
    assert violations and all(v.count == 41 and v.bound == 40 for v in violations)
