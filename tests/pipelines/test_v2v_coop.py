"""The v2v_coop pipeline: state round trips, option and input refusals, per-measurement reasons
(neighbour missing, stale, itself; dead reckoning before the heading is known), TOA equal to
metres, what a vehicle shares with its neighbours, and the paper's orderings on a few runs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.observations import (
    SPEED_OF_LIGHT,
    GnssFixObservation,
    GyroObservation,
    OdometerObservation,
    RsuObservation,
    V2vRangeObservation,
)
from edgepos.eval.v2v import METHODS, run_method
from edgepos.pipelines.base import NeighbourTrack, PipelineInputError, StaticEnvironment, TrackPoint
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.v2v import VEHICLE_IDS, make_run

PIPELINE = get_pipeline("v2v_coop")
COV = tuple(tuple(float(i == j) * (1.0 if i < 2 else 0.25) for j in range(4)) for i in range(4))


def epoch(t: float, x: float, y: float, peers: dict[str, float], toa: bool = False) -> list:
    out = [GnssFixObservation(t, x, y), GyroObservation(t, 0.0), OdometerObservation(t, distance=3.0)]
    for peer, distance in peers.items():
        if toa:
            out.append(V2vRangeObservation(t, peer, toa=distance / SPEED_OF_LIGHT))
        else:
            out.append(V2vRangeObservation(t, peer, range=distance))
    return out


def track(vehicle: str, t: float, x: float, y: float) -> NeighbourTrack:
    return NeighbourTrack(vehicle, (TrackPoint(t, x, y, 15.0, 0.0, COV),))


def session(method: str = "aug_ukf") -> bytes:
    return PIPELINE.create(PIPELINE.resolve_options({"method": method}), None)


def drive(method: str, steps: int, environment: StaticEnvironment, toa: bool = False) -> tuple[list, bytes]:
    state, fixes = session(method), []
    for k in range(steps):
        t = 0.2 * k
        batch = epoch(t, 15.0 * t, 0.0, {"north": math.hypot(30.0 - 15.0 * t, 20.0 - 15.0 * t * 0)}, toa)
        out, state = PIPELINE.process(state, batch, environment)
        fixes += out
    return fixes, state


def test_state_round_trips_bit_for_bit_and_processing_is_pure():
    environment = StaticEnvironment(tracks={"north": track("north", 0.0, 30.0, 20.0)}, vehicle_id="me")
    state = session()
    batch = epoch(0.0, 0.0, 0.0, {}) + epoch(0.2, 3.0, 0.1, {"north": 36.0})
    first = PIPELINE.process(state, batch, environment)
    second = PIPELINE.process(state, batch, environment)
    assert first[1] == second[1]
    assert [f.x for f in first[0]] == [f.x for f in second[0]]
    summary = PIPELINE.summarise(first[1])
    assert summary.initialised and summary.epochs == 2 and summary.options["method"] == "aug_ukf"


def test_bad_method_and_bad_times_are_refused_by_field():
    with pytest.raises(PipelineInputError) as error:
        PIPELINE.resolve_options({"method": "magic"})
    assert error.value.problems[0].field == "options.method"
    state = PIPELINE.process(session(), epoch(1.0, 0.0, 0.0, {}), StaticEnvironment())[1]
    # a time far after the rest of the batch (a clock error, beyond max_lead_s) and a time that is no number
    for bad_t in (30.0, float("nan")):
        batch = epoch(1.2, 3.0, 0.0, {}) + [GyroObservation(bad_t, 0.0)]
        with pytest.raises(PipelineInputError) as error:
            PIPELINE.process(state, batch, StaticEnvironment())
        assert [(p.index, p.field) for p in error.value.problems] == [(len(batch) - 1, "t")]
    # a kind the pipeline does not take, too late for the lag window: still refused by field
    batch = [RsuObservation(-5.0, "S000", 10.0, 0.0)] + epoch(1.2, 3.0, 0.0, {})
    with pytest.raises(PipelineInputError) as error:
        PIPELINE.process(state, batch, StaticEnvironment())
    assert [(p.index, p.field) for p in error.value.problems] == [(0, "kind")]


def test_time_going_back_is_late_or_too_late_and_a_batch_need_not_be_in_time_order():
    """Inside the lag window (max_delay_s 1 s) a measurement is filtered at its own time and the later fix
    is revised; beyond it, it is reported unused and the rest of the batch applied; within a batch the
    order does not matter (the pipeline once refused a batch out of time order)."""
    environment = StaticEnvironment()
    state = PIPELINE.process(session(), epoch(1.0, 0.0, 0.0, {}) + epoch(1.2, 3.0, 0.0, {}), environment)[1]
    fixes, late_state = PIPELINE.process(state, epoch(1.1, 1.5, 0.0, {}), environment)
    assert [(f.t, f.revised) for f in fixes] == [(1.1, False), (1.2, True)]
    assert all(u.used for u in fixes[0].measurements if u.kind == "gnss_fix")
    assert PIPELINE.summarise(late_state).t == 1.2
    batch = [GnssFixObservation(-1.0, 0.0, 0.0)] + epoch(1.4, 6.0, 0.0, {})
    fixes, _ = PIPELINE.process(state, batch, environment)
    assert [(f.t, f.revised) for f in fixes] == [(1.4, False)]
    uses = {u.index: u for u in fixes[0].measurements}
    assert sorted(uses) == list(range(len(batch)))
    assert not uses[0].used and uses[0].reason.startswith("too late: ") and uses[1].used
    in_order = epoch(1.4, 6.0, 0.0, {}) + epoch(1.6, 9.0, 0.0, {})
    backwards = epoch(1.6, 9.0, 0.0, {}) + epoch(1.4, 6.0, 0.0, {})
    fixes_in_order, state_in_order = PIPELINE.process(state, in_order, environment)
    fixes_backwards, state_backwards = PIPELINE.process(state, backwards, environment)
    assert state_backwards == state_in_order
    assert [f.t for f in fixes_backwards] == [1.4, 1.6] and not any(f.revised for f in fixes_backwards)
    assert [(f.x, f.y, f.vx, f.vy) for f in fixes_backwards] == [
        (f.x, f.y, f.vx, f.vy) for f in fixes_in_order
    ]


def test_each_unusable_range_says_why():
    environment = StaticEnvironment(
        tracks={"old": track("old", -5.0, 30.0, 0.0), "north": track("north", 0.2, 30.0, 20.0)},
        vehicle_id="me",
    )
    state = PIPELINE.process(session(), epoch(0.0, 0.0, 0.0, {}), environment)[1]
    batch = epoch(0.2, 3.0, 0.0, {"ghost": 10.0, "me": 1.0, "old": 20.0, "north": 33.0})
    fixes, _ = PIPELINE.process(state, batch, environment)
    reasons = {
        obs.peer_vehicle_id: use
        for obs, use in zip(batch, fixes[0].measurements)
        if isinstance(obs, V2vRangeObservation)
    }
    assert "no live session" in reasons["ghost"].reason
    assert "itself" in reasons["me"].reason
    assert "older than the measurement" in reasons["old"].reason
    assert reasons["north"].used


def test_dead_reckoning_waits_until_the_heading_is_known():
    fixes, _ = drive("gps_dr", 12, StaticEnvironment(vehicle_id="me"))
    first = [u for u in fixes[1].measurements if u.kind in ("gyro", "odometer")]
    assert first and not any(u.used for u in first)
    assert all("heading not yet known" in u.reason for u in first)
    assert all(u.used for u in fixes[-1].measurements if u.kind == "gyro")


def test_time_of_arrival_is_the_same_as_the_range_in_metres():
    environment = StaticEnvironment(tracks={"north": track("north", 0.0, 30.0, 20.0)}, vehicle_id="me")
    metres, _ = drive("aug_ukf", 6, environment)
    seconds, _ = drive("aug_ukf", 6, environment, toa=True)
    np.testing.assert_allclose([f.x for f in metres], [f.x for f in seconds], rtol=1e-9)


def test_a_cooperative_vehicle_shares_its_own_gnss_dr_estimate_not_the_cooperative_fix():
    environment = StaticEnvironment(tracks={"north": track("north", 0.0, 30.0, 20.0)}, vehicle_id="me")
    cooperative, _ = drive("aug_ukf", 8, environment)
    alone, _ = drive("gps_dr", 8, StaticEnvironment(vehicle_id="me"))
    last = cooperative[-1]
    assert last.shared is not None and (last.shared.x, last.shared.y) != (last.x, last.y)
    # The shared estimate saw what a GPS/DR filter sees (the UKF in place of the linearised DR update).
    assert math.hypot(last.shared.x - alone[-1].x, last.shared.y - alone[-1].y) < 0.5
    assert alone[-1].shared is None


def test_gps_method_returns_the_fix_itself():
    state = session("gps")
    fixes, state = PIPELINE.process(
        state, epoch(0.0, 1.0, 2.0, {}) + epoch(0.2, 4.0, 2.5, {}), StaticEnvironment()
    )
    assert (fixes[1].x, fixes[1].y) == (4.0, 2.5)
    assert (
        fixes[1].position_cov[0][0]
        == fixes[1].position_cov[1][1]
        == pytest.approx(PIPELINE.resolve_options({})["gps_std"] ** 2)
    )
    assert (
        0.0 < fixes[1].vx < 15.0 and 0.0 < fixes[1].vy < 2.5
    )  # a filter's velocity: towards the differences


def _gps_between_fixes(every: int, seed: int = 3) -> tuple[float, float, float, float]:
    """A straight drive at 15 m/s with 5 Hz epochs and a 3.8 m fix every ``every``-th epoch (white
    errors; the epochs between carry only a gyro reading): (position RMSE over all epochs, RMSE of the
    fixes, mean NEES of the position, RMS velocity error), after a 10 s start."""
    rng = np.random.default_rng(seed)
    sigma = 3.8
    state = PIPELINE.create(PIPELINE.resolve_options({"method": "gps", "gps_std": sigma}), None)
    errors, fix_errors, nees, velocity = [], [], [], []
    for k in range(600):
        t = 0.2 * k
        truth = np.array([15.0 * t, 0.0])
        batch: list = [GyroObservation(t, 0.0)]
        if k % every == 0:
            measured = truth + rng.normal(0.0, sigma, 2)
            batch.append(GnssFixObservation(t, float(measured[0]), float(measured[1])))
            if t >= 10.0:
                fix_errors.append(float(np.sum((measured - truth) ** 2)))
        (fix,), state = PIPELINE.process(state, batch, StaticEnvironment())
        if t >= 10.0:
            error = np.array([fix.x, fix.y]) - truth
            errors.append(float(error @ error))
            nees.append(float(error @ np.linalg.solve(np.array(fix.position_cov), error)))
            velocity.append((fix.vx - 15.0) ** 2 + fix.vy**2)
    return (
        math.sqrt(np.mean(errors)),
        math.sqrt(np.mean(fix_errors)),
        float(np.mean(nees)),
        math.sqrt(np.mean(velocity)),
    )


@pytest.mark.parametrize("every", [1, 5])
def test_gps_method_between_fixes_neither_drifts_nor_claims_too_much(every):
    """Between fixes the last fix moves on at a filtered velocity: the error stays near the fixes'
    own and the covariance says how large it is (mean NEES near 2 for 2 dof, not tens)."""
    rmse, fix_rmse, mean_nees, velocity_rms = _gps_between_fixes(every)
    assert rmse <= 1.25 * fix_rmse, (rmse, fix_rmse)
    assert 1.0 <= mean_nees <= 4.0, mean_nees
    differenced = 2.0 * 3.8 / (0.2 * every)  # RMS of velocities differenced from consecutive fixes
    assert velocity_rms < 0.5 * differenced, velocity_rms


@pytest.mark.parametrize("scenario", ["straight", "ring"])
def test_orderings_on_a_few_runs(scenario):
    totals = {method: 0.0 for method in METHODS}
    for r in range(4):
        run = make_run(11, r, scenario)
        for method in METHODS:
            squared, _, _ = run_method(run, method)
            totals[method] += float(squared[1:].sum())
    rmse = {m: math.sqrt(v / (4 * len(VEHICLE_IDS) * 99)) for m, v in totals.items()}
    assert rmse["GPS"] > rmse["GPS/DR"] > rmse["augUKF"], rmse
    assert rmse["UKF"] > rmse["augUKF"], rmse
