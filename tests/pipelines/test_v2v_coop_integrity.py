"""The cooperative integrity monitor on v2v_coop (and v2x_federated): a neighbour broadcasting a position 20 m off is
excluded within 1 s, the same fault raises the alarm when exclusion is off, the options are bounded
by field, and the state with the monitor round-trips exactly."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.eval.cooperative_integrity import run_method
from edgepos.eval.integrity import EXCLUDED
from edgepos.pipelines import v2v_coop
from edgepos.pipelines.base import PipelineInputError, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim import v2v as sim
from edgepos.sim.cooperative_faults import NeighbourFault
from edgepos.sim.faults import FaultEvent

PIPELINE = get_pipeline("v2v_coop")
RAW = v2v_coop.V2vCoopPipeline()  # its state as the pipeline encodes it, without the service's wrapping
FAULT = NeighbourFault(FaultEvent("veh-2", "position", 20.0, 8.0, 13.0), 0.5)


def lockstep(options: dict) -> list:
    """Every vehicle's fixes of run 0 of the straight scene with veh-2 broadcasting 20 m off from 8 s."""
    run = sim.make_run(0, 0, "straight")
    fixes: dict[str, list] = {vid: [] for vid in sim.VEHICLE_IDS}
    captured = []

    def spy(*args, **kwargs):
        captured.append(args)
        return original(*args, **kwargs)

    import edgepos.eval.cooperative_integrity as module

    original = module.tally
    module.tally = spy
    try:
        run_method(
            run, sim.VEHICLE_IDS, PIPELINE, options, {"gnss_fix", "gyro", "odometer", "v2v_range"}, FAULT, 5.0
        )
    finally:
        module.tally = original
    for vid, args in zip([v for v in sim.VEHICLE_IDS], captured, strict=True):
        fixes[vid] = args[0]
    return fixes["veh-1"]


@pytest.mark.parametrize("method", ["ukf", "aug_ukf"])
def test_a_neighbour_20_m_off_is_excluded_within_a_second(method):
    fixes = lockstep({"method": method, **sim.PAPER_OPTIONS, "integrity": True})
    before = [f for f in fixes if f.t < FAULT.event.start]
    assert all(f.protection_level is not None for f in before[1:])
    excluded = [
        f.t
        for f in fixes
        if FAULT.event.active(f.t)
        and any(u.kind == "v2v_range" and (u.reason or "").startswith(EXCLUDED) for u in f.measurements)
    ]
    assert excluded and excluded[0] - FAULT.event.start <= 1.0


def test_without_exclusion_the_same_fault_raises_the_alarm():
    fixes = lockstep({"method": "aug_ukf", "fault_exclusion": False, **sim.PAPER_OPTIONS, "integrity": True})
    alarms = [f.t for f in fixes if FAULT.event.active(f.t) and f.integrity == "alarm"]
    assert alarms and alarms[0] - FAULT.event.start <= 1.0
    assert not any(
        (u.reason or "").startswith(EXCLUDED) for f in fixes for u in f.measurements
    )  # reported, never acted on


def test_a_fix_above_the_alert_limit_is_in_alarm_and_the_gps_method_has_no_bound():
    fixes = lockstep({"method": "aug_ukf", "alert_limit_m": 0.5, **sim.PAPER_OPTIONS, "integrity": True})
    assert all(f.integrity == "alarm" for f in fixes[1:])
    gps = lockstep({"method": "gps", **sim.PAPER_OPTIONS, "integrity": True})
    assert {f.integrity for f in gps} == {"unavailable"} and all(f.protection_level is None for f in gps)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("integrity_risk", 0.5),
        ("integrity_risk", 1e-12),
        ("alert_limit_m", -1.0),
        ("fault_probability", 0.2),
        ("false_alarm_probability", 0.0),
    ],
)
def test_integrity_options_out_of_bounds_are_refused_by_field(field, value):
    with pytest.raises(PipelineInputError) as caught:
        PIPELINE.resolve_options({field: value})
    assert field in str(caught.value.problems)


def test_state_with_the_monitor_round_trips_exactly_and_an_old_state_runs_without_it():
    run = sim.make_run(0, 0, "straight")
    state = RAW.create(RAW.resolve_options({"method": "gps_dr", "integrity": True}), None)
    environment = StaticEnvironment(tracks={}, vehicle_id="veh-1")
    for k in range(10):
        _, state = RAW.process(state, run.observations[0][k], environment)
    assert v2v_coop._decode(state).to_bytes() == state
    again = RAW.process(state, run.observations[0][10], environment)
    assert again[1] == RAW.process(state, run.observations[0][10], environment)[1]
    assert again[0][-1].integrity in ("ok", "alarm") and np.isfinite(again[0][-1].protection_level)
    session = v2v_coop._decode(state)
    for name in ("integrity", "integrity_risk", "alert_limit_m"):
        del session.options[name]
    old = session.to_bytes()  # as stored before the monitor existed
    fixes, _ = RAW.process(old, run.observations[0][10], environment)
    assert fixes[-1].integrity == "unavailable" and fixes[-1].protection_level is None


def test_v2x_federated_excludes_the_same_neighbour_within_a_second():
    """The federated pipeline on the same run, with the V2V paper's noise (white 3.5 m fixes, 2 m ranges)."""
    import edgepos.eval.cooperative_integrity as module

    captured = []
    original = module.tally
    module.tally = lambda *args, **kwargs: captured.append(args) or original(*args, **kwargs)
    try:
        options = {**sim.PAPER_OPTIONS, "gps_std": sim.GPS_STD, "range_std": sim.RANGE_STD, "integrity": True}
        kinds = {"gnss_fix", "gyro", "odometer", "v2v_range"}
        run = sim.make_run(0, 0, "straight")
        run_method(run, sim.VEHICLE_IDS, get_pipeline("v2x_federated"), options, kinds, FAULT, 5.0)
    finally:
        module.tally = original
    fixes = captured[0][0]  # veh-1's
    excluded = [
        f.t
        for f in fixes
        if FAULT.event.active(f.t)
        and any(u.kind == "v2v_range" and (u.reason or "").startswith(EXCLUDED) for u in f.measurements)
    ]
    assert excluded and excluded[0] - FAULT.event.start <= 1.0
    settled = [
        f for f in fixes if 6.0 <= f.t < FAULT.event.start
    ]  # the filter settles over the first seconds
    assert settled and all(f.integrity == "ok" and f.protection_level < 5.0 for f in settled)


@pytest.mark.parametrize("name", ["v2v_coop", "v2x_federated"])
def test_the_cooperative_monitor_is_opt_in(name):
    """Off by default (docs/integrity.md: on the honest defaults it would put every fix in alarm at the
    5 m alert limit), unlike rsu_imu's and gnss_tight's."""
    assert get_pipeline(name).resolve_options({})["integrity"] is False
    assert get_pipeline("rsu_imu").resolve_options({})["integrity"] is True
    assert get_pipeline("gnss_tight").resolve_options({})["integrity"] is True
