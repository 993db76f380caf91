"""The cooperative monitor over time: a neighbour whose broadcast position jumps 20 m is excluded within
1 s whatever the direction, including across the line of sight where the range barely changes (the
geometry the epoch-wise separation test missed), it stays excluded for fault_exclusion_s, and the
session's holds round-trip in its state."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import state as state_format
from edgepos.eval.cooperative_integrity import run_method
from edgepos.eval.integrity import EXCLUDED
from edgepos.pipelines import v2v_coop, v2x_federated
from edgepos.pipelines.base import PipelineInputError, StaticEnvironment
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
