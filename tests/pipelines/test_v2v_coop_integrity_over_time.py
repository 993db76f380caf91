"""The cooperative monitor over time: a neighbour whose broadcast position jumps 20 m is excluded within
1 s whatever the direction, including across the line of sight where the range barely changes (the
geometry the epoch-wise separation test missed), it stays excluded for fault_exclusion_s, and the
session's holds round-trip in its state; the screen tests every track point newer than the last one
tested, once, and holds RSUs as well as neighbours."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import state as state_format
from edgepos.core.observations import RsuRangeObservation, V2vRangeObservation
from edgepos.eval.cooperative_integrity import run_method
from edgepos.eval.integrity import EXCLUDED
from edgepos.pipelines import v2v_coop, v2x_federated
from edgepos.pipelines.base import NeighbourTrack, PipelineInputError, StaticEnvironment, TrackPoint
from edgepos.pipelines.cooperative_integrity import screen_neighbours
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim import v2v as sim
from edgepos.sim.cooperative_faults import NeighbourFault
from edgepos.sim.faults import FaultEvent

KINDS = {"gnss_fix", "gyro", "odometer", "v2v_range"}
START, END = 8.0, 13.0
# veh-1 starts at (0, 0) and veh-2 at (20, 0) and they drive alike: an offset of 20 m at 120 degrees moves
# veh-2's point along the circle of radius 20 m about veh-1, so veh-1's range to it does not change at all.
ACROSS = NeighbourFault(FaultEvent("veh-2", "position", 20.0, START, END), 2.0 * math.pi / 3.0)


def vehicle_1(pipeline: str, options: dict, fault: NeighbourFault = ACROSS) -> list:
    """veh-1's fixes in run 0 of the straight scene, every vehicle in lockstep, veh-2 broadcasting ``fault``."""
    import edgepos.eval.cooperative_integrity as module

    captured = []
    original = module.tally
    module.tally = lambda *args, **kwargs: captured.append(args) or original(*args, **kwargs)
    try:
        run = sim.make_run(0, 0, "straight")
        run_method(run, sim.VEHICLE_IDS, get_pipeline(pipeline), options, KINDS, fault, 5.0)
    finally:
        module.tally = original
    return captured[0][0]


def reasons(fix) -> list[str]:
    """The reasons of a fix's range uses (veh-1 ranges to veh-2, veh-3, veh-4 in that order)."""
    return [u.reason or "" for u in fix.measurements if u.kind == "v2v_range"]


PAPER = {**sim.PAPER_OPTIONS, "integrity": True}
FEDERATED = {**sim.PAPER_OPTIONS, "gps_std": sim.GPS_STD, "range_std": sim.RANGE_STD, "integrity": True}


@pytest.mark.parametrize(
    ("pipeline", "options"),
    [
        ("v2v_coop", {**PAPER, "method": "ukf"}),
        ("v2v_coop", {**PAPER, "method": "aug_ukf"}),
        ("v2x_federated", FEDERATED),
    ],
)
def test_a_jump_across_the_line_of_sight_is_excluded_within_a_second_and_held(pipeline, options):
    fixes = vehicle_1(pipeline, options)
    first = next(f for f in fixes if f.t >= START and reasons(f)[0].startswith(EXCLUDED))
    assert first.t - START <= 1.0
    assert "broadcast track stepped" in reasons(first)[0]  # the step test, not the range's separation
    held = [f for f in fixes if first.t < f.t < first.t + 5.0 - 1e-9]
    assert held and all(reasons(f)[0].startswith(f"{EXCLUDED}: held out until") for f in held)
    assert not any(r.startswith(EXCLUDED) for f in fixes if f.t < START for r in reasons(f))
    assert not any(r.startswith(EXCLUDED) for f in fixes for r in reasons(f)[1:])  # veh-3 and veh-4 kept


def test_the_range_alone_could_not_tell(monkeypatch):
    """The fault leaves veh-1's range to veh-2 as it was; with the step test taken out, the epoch-wise
    separation test does not exclude veh-2 within the second (the miss this geometry used to be)."""
    run = sim.make_run(0, 0, "straight")
    k = round(START / sim.STEP) + 1
    x, q = run.positions[0, k], run.positions[1, k]
    moved = q + 20.0 * np.array([math.cos(ACROSS.direction), math.sin(ACROSS.direction)])
    assert abs(math.dist(x, moved) - math.dist(x, q)) < 1e-6
    import edgepos.pipelines.cooperative_integrity as glue

    monkeypatch.setattr(glue, "_track_jump", lambda track, seen, accel_std: (0.0, None))
    fixes = vehicle_1("v2v_coop", {**PAPER, "method": "aug_ukf"})
    assert not any(reasons(f)[0].startswith(EXCLUDED) for f in fixes if START <= f.t <= START + 1.0)


def test_a_zero_hold_excludes_for_the_detection_only_and_without_exclusion_the_jump_alarms():
    fixes = vehicle_1("v2v_coop", {**PAPER, "method": "aug_ukf", "fault_exclusion_s": 0.0})
    excluded = [f.t for f in fixes if reasons(f)[0].startswith(EXCLUDED)]
    assert excluded and excluded[0] - START <= 1.0
    assert not any("held out" in r for f in fixes for r in reasons(f))
    fixes = vehicle_1("v2v_coop", {**PAPER, "method": "aug_ukf", "fault_exclusion": False})
    alarms = [f.t for f in fixes if START <= f.t < END and f.integrity == "alarm"]
    assert alarms and alarms[0] - START <= 1.0
    assert not any(r.startswith(EXCLUDED) for f in fixes for r in reasons(f))


@pytest.mark.parametrize("value", [-1.0, 3601.0])
@pytest.mark.parametrize("name", ["v2v_coop", "v2x_federated"])
def test_fault_exclusion_s_out_of_bounds_is_refused_by_field(name, value):
    with pytest.raises(PipelineInputError) as caught:
        get_pipeline(name).resolve_options({"fault_exclusion_s": value})
    assert "fault_exclusion_s" in str(caught.value.problems)


@pytest.mark.parametrize(
    ("module", "raw", "options"),
    [
        (v2v_coop, v2v_coop.V2vCoopPipeline(), {**PAPER, "method": "aug_ukf"}),
        (v2x_federated, v2x_federated.V2xFederatedPipeline(), FEDERATED),
    ],
)
def test_holds_round_trip_exactly_and_a_state_without_them_decodes(module, raw, options):
    state = raw.create(raw.resolve_options(options), None)
    session = module._decode(state)
    session.held, session.seen = {"veh-2": 13.2000000001}, {"veh-2": 8.4, "veh-3": 8.6}
    blob = session.to_bytes()
    again = module._decode(blob)
    assert again.held == session.held and again.seen == session.seen and again.to_bytes() == blob
    meta, arrays = state_format.unpack(blob)
    del meta["held"], meta["seen"], meta["options"]["fault_exclusion_s"]
    old = module._decode(state_format.pack(meta, arrays))  # as stored before the holds existed
    assert old.held == {} and old.seen == {} and old.options["fault_exclusion_s"] == 0.0
    run = sim.make_run(0, 0, "straight")
    environment = StaticEnvironment(tracks={}, vehicle_id="veh-1")
    fixes, _ = raw.process(old.to_bytes(), run.observations[0][0], environment)
    assert fixes


def _track(jump_at: int | None, points: int = 10) -> NeighbourTrack:
    """A neighbour driving at 15 m/s along x, one point every 0.2 s, 20 m off sideways from point
    ``jump_at`` on."""
    cov = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 0.25, 0.0), (0.0, 0.0, 0.0, 0.25))
    return NeighbourTrack(
        "veh-2",
        tuple(
            TrackPoint(
                0.2 * k, 3.0 * k, 20.0 if jump_at is not None and k >= jump_at else 0.0, 15.0, 0.0, cov
            )
            for k in range(points)
        ),
    )


def _screen(held: dict, seen: dict, track: NeighbourTrack, t: float = 2.0):
    options = PIPELINE_OPTIONS
    observations = [V2vRangeObservation(t, "veh-2", range=30.0), RsuRangeObservation(t, "rsu-1", 12.0)]
    uses: dict = {}
    environment = StaticEnvironment(tracks={"veh-2": track}, vehicle_id="veh-1")
    excluded, alarm = screen_neighbours(options, held, seen, [0, 1], observations, environment, t, uses)
    return excluded, alarm, uses


PIPELINE_OPTIONS = v2x_federated.V2xFederatedPipeline().resolve_options({"integrity": True})


def test_every_step_newer_than_the_last_tested_point_is_screened():
    """Two points arrived since the last epoch (a batch): a jump at the earlier one is caught too; a
    jump already tested is not tested again, and a smooth track passes."""
    seen = {"veh-2": 1.5}  # points 0..7 (t <= 1.4) tested; 8 and 9 are new, the jump at 8
    excluded, alarm, uses = _screen({}, seen, _track(8))
    assert excluded == {"veh-2"} and not alarm and "broadcast track stepped" in (uses[0].reason or "")
    assert seen == {"veh-2": 1.8}
    excluded, _, uses = _screen({}, {"veh-2": 1.7}, _track(8))  # the jump (t = 1.6) was tested before
    assert excluded == frozenset() and uses == {}
    assert _screen({}, {"veh-2": 1.5}, _track(None))[0] == frozenset()


def test_a_held_rsu_or_neighbour_stays_out_until_its_hold_ends():
    held = {"rsu-1": 3.0, "veh-2": 1.9}  # veh-2's hold has ended at t = 2
    excluded, _, uses = _screen(held, {}, _track(None))
    assert excluded == {"rsu-1"} and "held out until t=3.00 s" in (uses[1].reason or "")
    assert held == {"rsu-1": 3.0} and 0 not in uses
