"""Physical plausibility (pipelines/plausibility.py): absurd but finite fixes are reported "diverged" and
reset the session, far initial states and jumps of the clock are refused, and nothing changes by a bit
when every fix is plausible.

The registry's pipelines are ``LagWindow(Plausible(inner))``: tests of what the plausibility layer does
with its own state (its envelope, states from before it, its time checks) take the registry pipeline's
``.inner`` (``plausible(name)``); tests of what a session gets go through the whole registry pipeline."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pytest
from edgepos.core.errors import NumericalError
from edgepos.core.observations import GnssFixObservation, GyroObservation, Observation
from edgepos.core.state import StateFormatError
from edgepos.pipelines import lag, plausibility, tracks
from edgepos.pipelines.base import (
    Environment,
    Fix,
    InitialState,
    MeasurementUse,
    OptionSpec,
    Pipeline,
    PipelineInputError,
    StateSummary,
    StaticEnvironment,
)
from edgepos.pipelines.lag import LagWindow
from edgepos.pipelines.options import resolve_options
from edgepos.pipelines.plausibility import Plausible, implausibility, unwrap, wrap
from edgepos.pipelines.registry import PIPELINES, get_pipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs
from hypothesis import given, settings
from hypothesis import strategies as st

NEW_OPTIONS = {"max_speed_mps", "max_acceleration_mps2", "site_radius_m", "max_time_jump_s", "on_divergence"}
LAG_OPTIONS = {"max_delay_s", "max_window_epochs", "max_lead_s"}


def plausible(name: str) -> Plausible:
    """The plausibility layer of the registry's pipeline ``name`` (registry: LagWindow(Plausible(inner)))."""
    pipeline = get_pipeline(name)
    assert isinstance(pipeline, LagWindow) and isinstance(pipeline.inner, Plausible)
    return pipeline.inner


def bare(name: str) -> Pipeline:
    """The registry's pipeline ``name`` without any wrapper."""
    return plausible(name).inner


def bare_options(options: Mapping[str, Any]) -> dict[str, Any]:
    """Resolved options of a registry pipeline without the wrappers' own."""
    return {k: v for k, v in options.items() if k not in NEW_OPTIONS | LAG_OPTIONS}


@pytest.fixture(scope="module")
def paper() -> tuple[list[list[Observation]], StaticEnvironment]:
    scenario = rsu_imu_paper_scenario()
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(7))
    return epochs, StaticEnvironment({rsu.id: rsu for rsu in scenario.rsus})


def flat(epochs: Sequence[Sequence[Observation]]) -> list[Observation]:
    return [o for epoch in epochs for o in epoch]


# -- a transparent inner pipeline: its fixes are the gnss_fix positions it is sent ---------------------
class Echo(Pipeline):
    """Position = the epoch's gnss_fix, velocity = difference with the previous epoch's (first fix:
    "initialised", velocity 0; then "tracking"); a gyro-only epoch is "uninitialised" before the first
    fix, else "predicted" at the last position. Counts the epochs it filters, over all instances."""

    name = "echo"
    description = "test double"
    measurement_kinds = ("gnss_fix", "gyro")
    publishes_track = True
    epochs_filtered = 0
    calls = 0

    def option_specs(self) -> list[OptionSpec]:
        return [
            OptionSpec("std", "number", 0.1, "position and velocity std", 0.0, 100.0),
            OptionSpec(
                "fail_beyond", "number", None, "NumericalError after a fix this far (m) east of the origin"
            ),
        ]

    def resolve_options(self, options: Mapping[str, Any] | None) -> dict[str, Any]:
        return resolve_options(self.option_specs(), options)

    def create(self, options: Mapping[str, Any], initial: InitialState | None) -> bytes:
        last = None if initial is None else [initial.x, initial.y]
        return json.dumps({"options": dict(options), "t": None, "last": last, "epochs": 0}).encode()

    def summarise(self, state: bytes) -> StateSummary:
        session = json.loads(state)
        return StateSummary(
            session["last"] is not None, session["t"], session["epochs"], {}, session["options"]
        )

    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        session = json.loads(state)
        if any(session["t"] is not None and o.t < session["t"] for o in observations):
            raise PipelineInputError([])
        Echo.calls += 1
        fixes = []
        for t in sorted({o.t for o in observations}):
            Echo.epochs_filtered += 1
            epoch = [i for i, o in enumerate(observations) if o.t == t]
            uses = [MeasurementUse(i, observations[i].kind, True) for i in epoch]
            gnss = [observations[i] for i in epoch if isinstance(observations[i], GnssFixObservation)]
            variance = session["options"]["std"] ** 2
            cov = [[variance if i == j else 0.0 for j in range(4)] for i in range(4)]
            if gnss:
                x, y = gnss[0].x, gnss[0].y
                limit = session["options"]["fail_beyond"]
                if limit is not None and session["last"] is not None and session["last"][0] > limit:
                    raise NumericalError("the test double fails after a run-off")
                if session["last"] is None or session["t"] is None:
                    status, vx, vy = "initialised", 0.0, 0.0
                else:
                    dt = t - session["t"]
                    status, vx, vy = "tracking", (x - session["last"][0]) / dt, (y - session["last"][1]) / dt
                session["last"] = [x, y]
                fix = Fix(
                    t,
                    status,
                    x,
                    y,
                    vx,
                    vy,
                    math.hypot(vx, vy),
                    position_cov=[r[:2] for r in cov[:2]],
                    kinematic_cov=cov,
                    measurements=uses,
                )
            elif session["last"] is None:
                fix = Fix(t, "uninitialised", measurements=uses)
            else:
                x, y = session["last"]
                fix = Fix(
                    t,
                    "predicted",
                    x,
                    y,
                    0.0,
                    0.0,
                    0.0,
                    position_cov=[r[:2] for r in cov[:2]],
                    kinematic_cov=cov,
                    measurements=uses,
                )
            session["t"] = t
            session["epochs"] += 1
            fixes.append(fix)
        return fixes, json.dumps(session).encode()


def echo(
    options: dict[str, Any] | None = None, initial: InitialState | None = None
) -> tuple[Plausible, bytes]:
    pipeline = Plausible(Echo())
    return pipeline, pipeline.create(pipeline.resolve_options(options), initial)


def track(*points: tuple[float, float, float]) -> list[Observation]:
    """gnss_fix observations at (t, x, y)."""
    return [GnssFixObservation(t, x, y) for t, x, y in points]


ENV = StaticEnvironment()


# -- options and registry -------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(PIPELINES))
def test_every_registered_pipeline_checks_plausibility_and_lists_the_options(name: str) -> None:
    pipeline = get_pipeline(name)
    inner = bare(name)  # and the registry pipeline is LagWindow(Plausible(inner))
    assert pipeline.name == plausible(name).name == name
    assert pipeline.publishes_track == plausible(name).publishes_track == inner.publishes_track
    assert pipeline.measurement_kinds == plausible(name).measurement_kinds == inner.measurement_kinds
    specs = {spec.name: spec for spec in pipeline.option_specs()}
    assert NEW_OPTIONS <= set(specs)
    assert {spec.name for spec in inner.option_specs()} | NEW_OPTIONS | LAG_OPTIONS == set(specs)
    resolved = pipeline.resolve_options({"max_speed_mps": 60, "on_divergence": "report"})
    assert resolved["max_speed_mps"] == 60.0 and resolved["on_divergence"] == "report"
    assert resolved["site_radius_m"] == 50_000.0 and resolved["max_time_jump_s"] == 3600.0
    assert {k: resolved[k] for k in LAG_OPTIONS} == lag.DEFAULTS
    assert pipeline.resolve_options(resolved) == resolved  # the session's options round-trip
    state = pipeline.create(resolved, None)
    summary = pipeline.summarise(state)
    assert summary.options["max_speed_mps"] == 60.0 and summary.options["on_divergence"] == "report"


def test_bad_options_of_the_wrapper_and_the_pipeline_are_named_together() -> None:
    pipeline = get_pipeline("rsu_imu")
    with pytest.raises(PipelineInputError) as caught:
        pipeline.resolve_options(
            {"max_speed_mps": 0.5, "on_divergence": "panic", "filter": "nope", "speed_limit": 3}
        )
    fields = {p.field: p.reason for p in caught.value.problems}
    assert set(fields) == {
        "options.max_speed_mps",
        "options.on_divergence",
        "options.filter",
        "options.speed_limit",
    }
    assert "max_time_jump_s" in fields["options.speed_limit"]  # the known options include the wrapper's


def test_a_pipeline_is_wrapped_once() -> None:
    with pytest.raises(TypeError):
        Plausible(plausible("rsu_imu"))
    with pytest.raises(TypeError):
        LagWindow(get_pipeline("rsu_imu"))


# -- initial states ---------------------------------------------------------------------------------------
def test_an_initial_state_far_outside_the_site_is_refused_naming_its_fields() -> None:
    pipeline = get_pipeline("rsu_imu")
    options = pipeline.resolve_options(None)
    with pytest.raises(PipelineInputError) as caught:
        pipeline.create(options, InitialState(1e6, 1e6, 10.0, 0.0))
    assert [(p.index, p.field) for p in caught.value.problems] == [
        (None, "initial_state.x"),
        (None, "initial_state.y"),
    ]
    assert "site_radius_m" in caught.value.problems[0].reason
    with pytest.raises(PipelineInputError) as caught:
        pipeline.create(options, InitialState(10.0, 0.0, 400.0, 0.0))
    assert [p.field for p in caught.value.problems] == ["initial_state.vx", "initial_state.vy"]
    # inside the bounds, or with a site radius that covers it: accepted
    pipeline.create(options, InitialState(30_000.0, -30_000.0, 40.0, 0.0))
    pipeline.create(pipeline.resolve_options({"site_radius_m": 2e6}), InitialState(1e6, 1e6, 10.0, 0.0))


def test_the_pipelines_own_refusal_of_an_initial_state_is_kept() -> None:
    pipeline = get_pipeline("gnss_tight")
    with pytest.raises(PipelineInputError) as caught:
        pipeline.create(pipeline.resolve_options(None), InitialState(1e6, 0.0, 0.0, 0.0))
    assert [p.field for p in caught.value.problems] == ["initial_state.x", "initial_state.y", "initial"]


# -- runaway filters -----------------------------------------------------------------------------------------
def test_a_filter_running_off_is_diverged_reset_and_starts_again(paper) -> None:
    """The issue's case: started at (1e6, 1e6) among RSUs near the origin, the filter's second fix went
    at 3e4 m/s and its later ones at 3e7 m/s, all "tracking". Now the first absurd fix is diverged,
    the session resets, and the rest of the batch starts again from the RSUs and tracks the truth."""
    epochs, environment = paper
    pipeline = get_pipeline("rsu_imu")
    initial = InitialState(1e6, 1e6, 10.0, 0.0)
    options = pipeline.resolve_options({"site_radius_m": 2e6})

    filt = bare("rsu_imu")
    runaway, _ = filt.process(filt.create(bare_options(options), initial), flat(epochs[:8]), environment)
    assert all(f.status == "tracking" for f in runaway) and max(f.speed for f in runaway) > 1e7

    fixes, state = pipeline.process(pipeline.create(options, initial), flat(epochs[:8]), environment)
    assert len(fixes) == 8
    diverged = [k for k, f in enumerate(fixes) if f.status == "diverged"]
    assert diverged == [1]
    fix = fixes[1]
    assert fix.speed > 1e4 and "max_speed_mps" in fix.divergence and "reset" in fix.divergence
    assert fixes[1] == dataclasses.replace(
        runaway[1], status="diverged", integrity="alarm", divergence=fix.divergence
    )
    assert fixes[2].status == "initialised" and [f.status for f in fixes[3:]] == ["tracking"] * 5
    # the re-filtered epochs name their measurements by the batch's indices
    assert [u.index for u in fixes[2].measurements] == [
        i for i in range(len(flat(epochs[:8]))) if flat(epochs[:8])[i].t == fixes[2].t
    ]
    assert all(f.divergence is None for k, f in enumerate(fixes) if k != 1)

    later, state = pipeline.process(state, flat(epochs[8:40]), environment)
    scenario = rsu_imu_paper_scenario()
    assert all(f.status == "tracking" for f in later)
    errors = [
        math.hypot(f.x - scenario.truth.x[k + 9], f.y - scenario.truth.y[k + 9]) for k, f in enumerate(later)
    ]
    assert max(errors) < 1.0, errors


def test_report_marks_every_runaway_fix_and_filters_on(paper) -> None:
    epochs, environment = paper
    pipeline = get_pipeline("rsu_imu")
    options = pipeline.resolve_options({"site_radius_m": 2e6, "on_divergence": "report"})
    initial = InitialState(1e6, 1e6, 10.0, 0.0)
    fixes, _ = pipeline.process(pipeline.create(options, initial), flat(epochs[:8]), environment)
    filt = bare("rsu_imu")
    own, _ = filt.process(filt.create(bare_options(options), initial), flat(epochs[:8]), environment)
    assert [f.status for f in fixes] == ["tracking"] + ["diverged"] * 7
    assert all("reported only" in f.divergence for f in fixes[1:])
    # the estimates are the filter's own: nothing but the status, the reason and the alarm changed
    assert fixes == [own[0]] + [
        dataclasses.replace(b, status="diverged", integrity="alarm", divergence=f.divergence)
        for b, f in zip(own[1:], fixes[1:])
    ]


def test_a_day_long_gap_the_filter_predicts_across_is_diverged(paper) -> None:
    """max_gap 86,400 s: the filter predicts across a long gap and lands ~1e8 m away; the fix is diverged
    and the next RSU epoch starts the session again. With the default max_time_jump_s the gap is refused.
    (The plausibility layer itself: its state is unwrapped below.)"""
    epochs, environment = paper
    pipeline = plausible("rsu_imu")
    start = InitialState(0.0, rsu_imu_paper_scenario().truth.y[0], 10.0, 0.0)
    gap = 80_000.0

    def late(k: int, gyro_only: bool = False) -> list[Observation]:
        return [dataclasses.replace(o, t=o.t + gap) for o in epochs[k] if not gyro_only or o.kind == "gyro"]

    options = pipeline.resolve_options({"max_gap": 86_400, "max_time_jump_s": 86_400})
    _, state = pipeline.process(pipeline.create(options, start), flat(epochs[:5]), environment)
    bare, _ = pipeline.inner.process(unwrap(state)[1], late(5, gyro_only=True), environment)
    assert bare[0].status == "tracking" and math.hypot(bare[0].x, bare[0].y) > 1e7  # the gyro was "used"
    # (in one batch the filter fails on the RSUs after the gap: the run-off fix is reset before that)
    fixes, state = pipeline.process(state, late(5, gyro_only=True) + late(6), environment)
    assert [f.status for f in fixes] == ["diverged", "initialised"]
    assert "site_radius_m" in fixes[0].divergence

    _, state = pipeline.process(
        pipeline.create(pipeline.resolve_options(None), start), flat(epochs[:5]), environment
    )
    batch = late(5)
    with pytest.raises(PipelineInputError) as caught:
        pipeline.process(state, batch, environment)
    assert [(p.index, p.field) for p in caught.value.problems] == [(i, "t") for i in range(len(batch))]
    assert "max_time_jump_s" in caught.value.problems[0].reason


# -- times ------------------------------------------------------------------------------------------------------
def test_a_jump_to_the_largest_time_is_refused_and_the_session_goes_on(paper) -> None:
    """A session whose clock reached 1e10 (the largest t the API takes) could never take another epoch:
    such a jump is refused, the state is untouched, and the next correct batch is filtered. (The
    plausibility layer; in the registry pipeline the lag window's max_lead_s refuses a jump within a batch
    first, naming the same observations.)"""
    epochs, environment = paper
    pipeline = plausible("rsu_imu")
    _fixes, state = pipeline.process(
        pipeline.create(pipeline.resolve_options(None), None), flat(epochs[:3]), environment
    )
    far = [dataclasses.replace(o, t=1e10) for o in epochs[3]]
    with pytest.raises(PipelineInputError) as caught:
        pipeline.process(state, far, environment)
    assert {p.index for p in caught.value.problems} == set(range(len(far)))
    assert all(p.field == "t" and "open a new session" in p.reason for p in caught.value.problems)
    # within one batch too (from its previous epoch), naming only the jumping epoch's observations
    with pytest.raises(PipelineInputError) as caught:
        pipeline.process(state, list(epochs[3]) + far, environment)
    assert {p.index for p in caught.value.problems} == set(range(len(epochs[3]), len(epochs[3]) + len(far)))
    assert "previous epoch" in caught.value.problems[0].reason
    registry = get_pipeline("rsu_imu")
    registry_state = registry.create(registry.resolve_options(None), None)
    _, registry_state = registry.process(registry_state, flat(epochs[:3]), environment)
    for batch in (far, list(epochs[3]) + far):
        with pytest.raises(PipelineInputError) as caught:
            registry.process(registry_state, batch, environment)
        assert {p.index for p in caught.value.problems} == set(range(len(batch) - len(far), len(batch)))
        assert all(p.field == "t" for p in caught.value.problems)
    # and in a fresh session, whose clock is unset, between its epochs
    fresh = pipeline.create(pipeline.resolve_options(None), None)
    with pytest.raises(PipelineInputError):
        pipeline.process(fresh, list(epochs[0]) + far, environment)
    pipeline.process(fresh, far, environment)  # a first epoch may be at any time
    more, _ = pipeline.process(state, flat(epochs[3:6]), environment)
    assert [f.status for f in more] == ["tracking"] * 3
    assert pipeline.summarise(state).t == epochs[2][0].t


def test_after_a_reset_at_the_end_of_a_batch_time_still_only_goes_forward() -> None:
    pipeline, state = echo({"site_radius_m": 1000})
    fixes, state = pipeline.process(state, track((1.0, 0.0, 0.0), (2.0, 5000.0, 0.0)), ENV)
    assert [f.status for f in fixes] == ["initialised", "diverged"]
    assert pipeline.summarise(state).t == 2.0 and pipeline.summarise(state).initialised is False
    with pytest.raises(PipelineInputError) as caught:
        pipeline.process(state, track((1.5, 0.0, 0.0)), ENV)
    assert [(p.index, p.field) for p in caught.value.problems] == [(0, "t")]
    assert "older than the session's last epoch t=2.0" in caught.value.problems[0].reason
    fixes, state = pipeline.process(state, track((2.0, 1.0, 0.0), (3.0, 11.0, 0.0)), ENV)
    assert [f.status for f in fixes] == ["initialised", "tracking"]
    with pytest.raises(PipelineInputError):  # the inner pipeline's own clock again
        pipeline.process(state, track((2.5, 0.0, 0.0)), ENV)


# -- each check -------------------------------------------------------------------------------------------------
def _fix(
    t: float, x: float, y: float, vx: float, vy: float, std: float = 0.1, status: str = "tracking"
) -> Fix:
    variance = std**2
    cov = [[variance if i == j else 0.0 for j in range(4)] for i in range(4)]
    return Fix(
        t, status, x, y, vx, vy, math.hypot(vx, vy), position_cov=[r[:2] for r in cov[:2]], kinematic_cov=cov
    )


OPTIONS = dict(plausibility.DEFAULTS)


def _after(previous: Fix, fix: Fix, **options: Any) -> str | None:
    return implausibility(fix, plausibility._point(previous), {**OPTIONS, **options})


def test_acceleration_beyond_the_bound_and_the_filters_uncertainty_is_implausible() -> None:
    before = _fix(0.0, 0.0, 0.0, 20.0, 0.0)
    assert _after(before, _fix(0.1, 2.0, 0.0, 20.0, 0.0)) is None
    assert _after(before, _fix(0.1, 2.0, 0.0, 25.0, 0.0)) is None  # 50 m/s^2: a filter's correction
    reason = _after(before, _fix(0.1, 2.0, 0.0, 20.0, 30.0))  # 300 m/s^2
    assert reason is not None and reason.startswith("acceleration 300 m/s^2 over 0.1 s")
    assert _after(before, _fix(0.1, 2.0, 0.0, 20.0, 30.0), max_acceleration_mps2=400) is None
    uncertain = _fix(0.1, 2.0, 0.0, 20.0, 30.0, std=10.0)  # the filter says its velocity is unsure
    assert _after(before, uncertain) is None
    # a fix that starts a new track is not compared with the old one
    assert _after(before, _fix(0.1, 2.0, 0.0, 20.0, 30.0, status="initialised")) is None


def test_a_position_jump_no_vehicle_could_make_is_implausible() -> None:
    before = _fix(0.0, 0.0, 0.0, 20.0, 0.0)
    assert _after(before, _fix(0.1, 2.0, 0.0, 20.0, 0.0)) is None
    assert _after(before, _fix(0.1, 6.0, 0.0, 20.0, 0.0)) is None  # a 4 m correction in 0.1 s
    reason = _after(before, _fix(0.1, 2.0, 300.0, 20.0, 0.0))
    assert reason is not None and reason.startswith("position jumped 300 m in 0.1 s")
    assert _after(before, _fix(10.0, 200.0, 300.0, 20.0, 0.0)) is None  # possible in 10 s


def test_speed_and_site_radius() -> None:
    assert implausibility(_fix(0.0, 0.0, 0.0, 149.0, 0.0), None, OPTIONS) is None
    assert "max_speed_mps 150" in implausibility(_fix(0.0, 0.0, 0.0, 151.0, 0.0), None, OPTIONS)
    assert implausibility(_fix(0.0, 0.0, 0.0, 151.0, 0.0, std=1.0), None, OPTIONS) is None  # 4 sigma
    assert implausibility(_fix(0.0, 49_000.0, 0.0, 0.0, 0.0), None, OPTIONS) is None
    reason = implausibility(_fix(0.0, 40_000.0, 40_000.0, 0.0, 0.0, std=1e4), None, OPTIONS)
    assert reason == "position 5.657e+04 m from the site origin is beyond site_radius_m 50000 m"
    assert implausibility(Fix(0.0, "uninitialised"), None, OPTIONS) is None


def test_the_previous_batch_s_last_fix_is_compared_with() -> None:
    pipeline, state = echo()
    fixes, state = pipeline.process(state, track((0.0, 0.0, 0.0), (1.0, 20.0, 0.0)), ENV)
    assert [f.status for f in fixes] == ["initialised", "tracking"]
    fixes, state = pipeline.process(state, track((1.1, 22.0, 0.0), (1.2, 24.0, 0.0)), ENV)
    assert [f.status for f in fixes] == ["tracking", "tracking"]
    fixes, state = pipeline.process(state, track((1.3, 24.0, 60.0), (1.4, 26.0, 60.0)), ENV)  # jump
    assert [f.status for f in fixes] == ["diverged", "initialised"]
    assert fixes[0].divergence.startswith("speed 600 m/s")


# -- reset mechanics ---------------------------------------------------------------------------------------------
def test_a_reset_refilters_the_rest_of_the_batch_with_its_indices() -> None:
    pipeline, state = echo()
    batch = [GyroObservation(0.5, 0.0)] + track((1.0, 0.0, 0.0), (2.0, 20.0, 0.0), (3.0, 9000.0, 0.0))
    batch += [GyroObservation(4.0, 0.0)] + track((4.0, 30.0, 0.0), (5.0, 50.0, 0.0))
    Echo.calls = 0
    fixes, state = pipeline.process(state, batch, ENV)
    assert Echo.calls == 2  # one more call, only because of the reset
    assert [f.status for f in fixes] == [
        "uninitialised",
        "initialised",
        "tracking",
        "diverged",
        "initialised",
        "tracking",
    ]
    assert [[u.index for u in f.measurements] for f in fixes] == [[0], [1], [2], [3], [4, 5], [6]]
    assert fixes[3].x == 9000.0 and fixes[4].vx == 0.0 and fixes[5].vx == 20.0


def test_a_run_off_the_filter_then_fails_on_is_reset_rather_than_failing_the_batch() -> None:
    """The inner pipeline raises on the epoch after a run-off fix (as a real filter can, its covariance
    ruined): the batch is filtered again a few epochs at a time, the run-off fix is diverged and reset,
    and the rest goes on from the fresh state. A failure with nothing implausible before it stays one."""
    pipeline, state = echo({"fail_beyond": 5000})
    batch = track((1.0, 0.0, 0.0), (2.0, 9000.0, 0.0), (3.0, 20.0, 0.0), (4.0, 40.0, 0.0))
    with pytest.raises(NumericalError):
        pipeline.inner.process(unwrap(state)[1], batch, ENV)
    fixes, state = pipeline.process(state, batch, ENV)
    assert [f.status for f in fixes] == ["initialised", "diverged", "initialised", "tracking"]
    assert [[u.index for u in f.measurements] for f in fixes] == [[0], [1], [2], [3]]
    with pytest.raises(NumericalError):  # report: the filter goes on from the run-off, and fails
        pipeline.process(echo({"fail_beyond": 5000, "on_divergence": "report"})[1], batch, ENV)
    pipeline, state = echo({"fail_beyond": 50})
    with pytest.raises(NumericalError):  # 30 m/s is plausible: the failure is the filter's own
        pipeline.process(
            state, track((1.0, 0.0, 0.0), (2.0, 30.0, 0.0), (3.0, 60.0, 0.0), (4.0, 90.0, 0.0)), ENV
        )


def test_a_batch_diverging_at_every_epoch_costs_a_few_plain_runs() -> None:
    pipeline, state = echo({"site_radius_m": 10})
    count = 200
    Echo.epochs_filtered = 0
    fixes, state = pipeline.process(state, track(*[(float(k), 1000.0 + k, 0.0) for k in range(count)]), ENV)
    assert [f.status for f in fixes] == ["diverged"] * count
    assert [f.measurements[0].index for f in fixes] == list(range(count))
    assert Echo.epochs_filtered <= 3 * count  # not count**2 / 2


def test_diverged_fixes_are_not_published() -> None:
    pipeline, state = echo()
    fixes, _ = pipeline.process(
        state, track((0.0, 0.0, 0.0), (0.1, 1.0, 0.0), (0.2, 500.0, 0.0), (0.3, 501.0, 0.0)), ENV
    )
    assert [f.status for f in fixes] == ["initialised", "tracking", "diverged", "initialised"]
    assert fixes[2].kinematic_cov is not None
    published = tracks.publish("car", None, fixes)
    assert [p.t for p in published.points] == [0.0, 0.1, 0.3]


# -- state --------------------------------------------------------------------------------------------------------
def test_a_state_written_before_the_wrapper_is_still_read(paper) -> None:
    """Sessions opened before plausibility checks existed carry the bare pipeline's state: the plausibility
    layer goes on with the default options and gives it the envelope with its next batch, with the very
    same fixes. (The registry pipeline's lag window refuses a state without its own envelope: below.)"""
    epochs, environment = paper
    pipeline = plausible("rsu_imu")
    options = pipeline.resolve_options(None)
    old = pipeline.inner.create({k: v for k, v in options.items() if k not in NEW_OPTIONS}, None)
    _, old = pipeline.inner.process(old, flat(epochs[:4]), environment)
    summary = pipeline.summarise(old)
    assert summary.t == epochs[3][0].t and summary.options == options
    expected, _ = pipeline.inner.process(old, flat(epochs[4:9]), environment)
    fixes, new = pipeline.process(old, flat(epochs[4:9]), environment)
    assert fixes == expected and new.startswith(plausibility.MAGIC)
    assert pipeline.process(old, [], environment) == ([], old)
    with pytest.raises(PipelineInputError):  # its clock is known: a jump is refused
        pipeline.process(old, [dataclasses.replace(o, t=1e10) for o in epochs[4]], environment)
    for older in (old, new):  # written before the lag window: the session must be opened anew
        with pytest.raises(StateFormatError, match="open a new session"):
            get_pipeline("rsu_imu").process(older, flat(epochs[9:10]), environment)


def test_the_envelope_round_trips_and_damage_is_a_state_format_error(paper) -> None:
    epochs, environment = paper
    pipeline = plausible("rsu_imu")
    _, state = pipeline.process(
        pipeline.create(pipeline.resolve_options(None), None), flat(epochs[:3]), environment
    )
    envelope, inner = unwrap(state)
    assert wrap(envelope, inner) == state
    assert envelope.t == epochs[2][0].t and envelope.last is not None and envelope.last.t == envelope.t
    assert pipeline.process(state, [], environment) == ([], state)
    policy = len(plausibility.MAGIC) + 1 + 4 * 8  # the on_divergence byte
    damaged_policy = state[:policy] + b"\x07" + state[policy + 1 :]
    for damaged in (state[:6], state[:60], state[:-3], b"EPPL\x02" + state[5:], damaged_policy):
        with pytest.raises(StateFormatError):
            pipeline.process(damaged, flat(epochs[3:4]), environment)
    # another pipeline's state behind the envelope is still refused by the pipeline itself
    other = plausible("v2v_coop")
    with pytest.raises(StateFormatError):
        pipeline.process(other.create(other.resolve_options(None), None), flat(epochs[3:4]), environment)


# -- nothing changes when every fix is plausible ------------------------------------------------------------------
BATCHES = [(0, 1), (1, 7), (8, 20), (28, 3), (31, 200), (231, 569)]


def inner_state(wrapped: Pipeline, state: bytes) -> bytes:
    """The bare pipeline's state inside a plausibility layer's (or a registry pipeline's) state."""
    if isinstance(wrapped, LagWindow):
        state = lag._unpack(state).current
    return unwrap(state)[1]


@pytest.mark.parametrize("layer", ["plausible", "registry"])
@pytest.mark.parametrize("options", [{}, {"filter": "ekf", "rsu_handling": "average"}])
@pytest.mark.parametrize("start", [False, True])
def test_the_wrapper_changes_no_bit_of_plausible_fixes(paper, options: dict, start: bool, layer: str) -> None:
    """The plausibility layer alone, and the registry's LagWindow(Plausible(...)) on data in time order."""
    epochs, environment = paper
    assert sum(count for _, count in BATCHES) == len(epochs)
    wrapped = plausible("rsu_imu") if layer == "plausible" else get_pipeline("rsu_imu")
    filt = bare("rsu_imu")
    truth = rsu_imu_paper_scenario().truth
    initial = InitialState(truth.x[0], truth.y[0], truth.vx[0], truth.vy[0]) if start else None
    resolved = wrapped.resolve_options(options)
    state_w = wrapped.create(resolved, initial)
    state_b = filt.create(filt.resolve_options(options), initial)
    assert inner_state(wrapped, state_w) == state_b
    for first, count in BATCHES:
        batch = flat(epochs[first : first + count])
        fixes_w, state_w = wrapped.process(state_w, batch, environment)
        fixes_b, state_b = filt.process(state_b, batch, environment)
        assert fixes_w == fixes_b
        assert inner_state(wrapped, state_w) == state_b
    assert all(f.status in ("initialised", "tracking") for f in fixes_w)


@pytest.mark.parametrize("method", ["gps", "gps_dr", "ukf", "aug_ukf"])
def test_the_wrapper_changes_no_bit_of_cooperative_fixes(method: str) -> None:
    """v2v_coop over the paper's ring scenario: every vehicle a session, ranging to the others' tracks."""
    from edgepos.sim import v2v

    run = v2v.make_run(3, 0, "ring")
    wrapped = get_pipeline("v2v_coop")  # both wrappers: lag window and plausibility, on data in time order
    options = wrapped.resolve_options({"method": method})
    sessions = {
        which: (pipeline, {vid: pipeline.create(opts, None) for vid in v2v.VEHICLE_IDS}, {})
        for which, pipeline, opts in (
            ("wrapped", wrapped, options),
            ("bare", bare("v2v_coop"), bare_options(options)),
        )
    }
    for k in range(len(run.times)):
        step = {}
        for which, (pipeline, states, published) in sessions.items():
            snapshot = dict(published)
            for i, vid in enumerate(v2v.VEHICLE_IDS):
                fixes, states[vid] = pipeline.process(
                    states[vid], run.observations[i][k], StaticEnvironment(tracks=snapshot, vehicle_id=vid)
                )
                step[which, vid] = fixes
                published[vid] = tracks.publish(vid, published.get(vid), fixes) or published.get(vid)
        for vid in v2v.VEHICLE_IDS:
            assert step["wrapped", vid] == step["bare", vid]
            assert all(f.status != "diverged" for f in step["wrapped", vid])


def test_the_wrapper_changes_no_bit_of_federated_fixes() -> None:
    from edgepos.sim import federated

    target = federated.make_run(3, 0, "multipath")
    wrapped = get_pipeline(
        "v2x_federated"
    )  # both wrappers: lag window and plausibility, on data in time order
    filt = bare("v2x_federated")
    options = wrapped.resolve_options(None)
    state_w, state_b = wrapped.create(options, None), filt.create(bare_options(options), None)
    for epoch in target.observations:
        environment = StaticEnvironment(vehicle_id="target")
        fixes_w, state_w = wrapped.process(state_w, epoch, environment)
        fixes_b, state_b = filt.process(state_b, epoch, environment)
        assert fixes_w == fixes_b and all(f.status != "diverged" for f in fixes_w)
    assert inner_state(wrapped, state_w) == state_b


# -- the quick paths of the checks against their plain definitions ---------------------------------
TIMES = st.one_of(
    st.floats(-5.0, 5.0), st.integers(-5, 5), st.sampled_from([math.nan, math.inf, -math.inf, 1e10, 0.0])
)


@settings(max_examples=300, deadline=None)
@given(
    times=st.lists(TIMES, max_size=6),
    last=st.one_of(st.none(), st.floats(-5.0, 5.0)),
    bound=st.sampled_from([1.0, 3.0, 3600.0]),
)
def test_the_time_check_of_the_usual_batch_agrees_with_its_definition(times, last, bound) -> None:
    """``_check_times`` answers a batch of floats in one pass; whatever the times (ints, NaN, infinities,
    jumps), it returns the latest finite time or refuses exactly as sorting the finite times does."""
    envelope = plausibility._Envelope({**plausibility.DEFAULTS, "max_time_jump_s": bound}, last, None, False)
    observations = [GyroObservation(t, 0.0) for t in times]
    finite = sorted({t for t in times if plausibility.is_finite_number(t)})
    previous, jump = last, False
    for t in finite:
        jump = jump or (previous is not None and t - previous > bound)
        previous = t if previous is None or t > previous else previous
    if jump:
        with pytest.raises(PipelineInputError):
            plausibility._check_times(envelope, observations)
    else:
        assert plausibility._check_times(envelope, observations) == (finite[-1] if finite else None)


@pytest.mark.parametrize(
    ("field", "bad"),
    [
        (f, b)
        for f in ("t", "x", "y", "vx", "vy")
        for b in (math.nan, math.inf, -math.inf, None)
        if (f, b) != ("t", None)
    ],
)
def test_a_fix_with_anything_not_finite_is_not_kept_for_the_next_check(field: str, bad: float | None) -> None:
    fix = Fix(t=1.0, status="tracking", x=2.0, y=3.0, vx=4.0, vy=5.0, position_cov=[[1.0, 0.0], [0.0, 1.0]])
    point = plausibility._point(dataclasses.replace(fix, **{field: bad}))
    if bad is None and field in ("vx", "vy"):
        assert point is not None and getattr(point, field) is None
    else:
        assert point is None
    assert plausibility._point(fix) == plausibility._Point(1.0, 2.0, 3.0, 4.0, 5.0, 2.0, 0.0)
    huge = dataclasses.replace(fix, x=1e308, y=1e308)  # finite, though their sum is not
    assert plausibility._point(huge) is not None


@pytest.mark.parametrize(
    ("position", "velocity"), [(-1e-12, 0.5), (0.25, -3e-15), (-1e-9, -2e-9), (0.0, -0.0)]
)
def test_a_negative_variance_is_kept_as_zero_and_the_other_as_it_is(position: float, velocity: float) -> None:
    """Round-off can leave a covariance's trace a hair below zero: the kept point holds max(variance, 0)
    of each (a negative zero stays as max leaves it)."""
    fix = Fix(
        t=1.0,
        status="tracking",
        x=2.0,
        y=3.0,
        vx=4.0,
        vy=5.0,
        position_cov=[[position, 0.0], [0.0, 0.0]],
        kinematic_cov=[[0.0] * 4, [0.0] * 4, [0.0, 0.0, velocity, 0.0], [0.0] * 4],
    )
    point = plausibility._point(fix)
    assert point is not None
    for kept, trace in ((point.position_var, position + 0.0), (point.velocity_var, velocity + 0.0)):
        want = max(trace, 0.0)
        assert kept == want and math.copysign(1.0, kept) == math.copysign(1.0, want)


NUMBERS = st.one_of(st.floats(-300.0, 300.0), st.sampled_from([math.nan, math.inf, 1e6, 0.0]))


@settings(max_examples=300, deadline=None)
@given(
    now=st.tuples(NUMBERS, NUMBERS, NUMBERS, st.one_of(st.none(), NUMBERS), st.floats(0.0, 1e4)),
    before=st.one_of(
        st.none(), st.tuples(NUMBERS, NUMBERS, NUMBERS, st.one_of(st.none(), NUMBERS), st.floats(0.0, 1e4))
    ),
    status=st.sampled_from(["tracking", "initialised"]),
)
def test_judging_a_fix_at_once_agrees_with_the_check_and_the_kept_point(now, before, status) -> None:
    """What the judge asks of every fix (``_judged``, the variances read once) is exactly
    ``implausibility`` and ``_point`` asked one after the other."""

    def fix_of(t: float, values: tuple) -> Fix:
        x, y, vx, vy, var = values
        cov = [[var, 0.0], [0.0, var]]
        kinematic = [[var if i == j else 0.0 for j in range(4)] for i in range(4)]
        return Fix(t=t, status=status, x=x, y=y, vx=vx, vy=vy, position_cov=cov, kinematic_cov=kinematic)

    last = None if before is None else plausibility._point(fix_of(0.0, before))
    fix = fix_of(0.05, now)
    assert plausibility._judged(fix, last, plausibility._bounds(OPTIONS)) == (
        implausibility(fix, last, OPTIONS),
        plausibility._point(fix),
    )
