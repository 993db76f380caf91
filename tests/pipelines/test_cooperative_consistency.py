"""The cooperative pipelines' consistency scale (option consistency_scale): an over-confident filter's
reported covariance and protection level grow until its error is within them, while its positions and
what it publishes for its neighbours stay as they were; the scale round-trips in the session's state, a
state stored before it decodes with none (and the option off), and the option's bounds are enforced."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core import state as state_format
from edgepos.core.consistency import ConsistencyScale
from edgepos.eval.cooperative_integrity import run_method
from edgepos.pipelines import tracks, v2v_coop, v2x_federated
from edgepos.pipelines.base import PipelineInputError, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim import v2v as sim

PIPELINE = get_pipeline("v2v_coop")
OWN = {"gnss_fix", "gyro", "odometer"}


def _drive(options: dict, scene: str = "ring") -> tuple[list, list]:
    """Each vehicle of run 0 of ``scene`` alone (GNSS and dead reckoning): its fixes and the truth."""
    run = sim.make_run(0, 0, scene)
    resolved = PIPELINE.resolve_options(options)
    fixes, truth = [], []
    for i in range(len(sim.VEHICLE_IDS)):
        state = PIPELINE.create(resolved, None)
        for k in range(len(run.times)):
            batch = [o for o in run.observations[i][k] if o.kind in OWN]
            out, state = PIPELINE.process(state, batch, StaticEnvironment(vehicle_id=sim.VEHICLE_IDS[i]))
            fixes.append(out[-1])
            truth.append(run.positions[i, k])
    return fixes, truth


def _figures(fixes: list, truth: list) -> tuple[float, int]:
    """Mean NEES from the fifth epoch of each vehicle on, and the misleading epochs (error above the
    protection level while ok)."""
    nees, misleading = [], 0
    for n, (fix, (x, y)) in enumerate(zip(fixes, truth, strict=True)):
        error = np.array([fix.x - x, fix.y - y])
        if n % sim.STEPS >= 5:
            nees.append(float(error @ np.linalg.solve(np.array(fix.position_cov), error)))
        misleading += fix.integrity == "ok" and float(np.hypot(*error)) > fix.protection_level
    return float(np.mean(nees)), misleading


def test_an_over_confident_filter_reports_a_covariance_its_error_fits() -> None:
    # 0.03 m/s^2 of acceleration change where the ring's turns need several: the filter lags in every
    # turn while its covariance stays small (mean NEES 26 where 2 is consistent; 6.6 with the scale, measured
    # since dead reckoning waits for a 5-sigma heading, 30 and 4.8 before).
    options = {"method": "gps_dr", **sim.PAPER_OPTIONS, "accel_std": 0.03, "integrity": True}
    before, truth = _drive(options)
    after, _ = _drive({**options, "consistency_scale": True})
    nees_before, misleading_before = _figures(before, truth)
    nees_after, misleading_after = _figures(after, truth)
    assert nees_before > 20.0 and misleading_before > 50
    assert nees_after < nees_before / 3.0 and misleading_after == 0
    assert after[0].integrity == "unavailable"  # nothing bounds the scale before the first fixes
    assert [(f.x, f.y, f.vx, f.vy) for f in after] == [(f.x, f.y, f.vx, f.vy) for f in before]
    # what the vehicle publishes is the filter's own estimate, as without the scale
    assert tracks.track_points(after) == tracks.track_points(before)
    assert any(
        np.array(a.position_cov)[0, 0] > 2.0 * np.array(b.position_cov)[0, 0] for a, b in zip(after, before)
    )


def test_a_consistent_filter_is_left_about_as_it_was() -> None:
    options = {"method": "gps_dr", **sim.PAPER_OPTIONS, "integrity": True}
    before, truth = _drive(options, "straight")
    after, _ = _drive({**options, "consistency_scale": True}, "straight")
    nees_before, _ = _figures(before, truth)
    nees_after, misleading = _figures(after, truth)
    assert 1.0 <= nees_after <= nees_before <= 4.0 and misleading == 0


@pytest.mark.parametrize(
    ("name", "options"),
    [
        ("v2v_coop", {**sim.PAPER_OPTIONS, "method": "aug_ukf"}),
        ("v2x_federated", {**sim.PAPER_OPTIONS, "gps_std": sim.GPS_STD, "range_std": sim.RANGE_STD}),
    ],
)
def test_cooperative_fixes_keep_their_positions_and_their_bound_only_grows(name: str, options: dict) -> None:
    run = sim.make_run(1, 0, "ring")
    pipeline = get_pipeline(name)
    kinds = OWN | {"v2v_range"}
    plain = {**options, "integrity": True}
    errors_before, errors_after = np.zeros(3), np.zeros(3)
    before = run_method(run, sim.VEHICLE_IDS, pipeline, plain, kinds, None, 5.0, errors_before)
    after = run_method(
        run, sim.VEHICLE_IDS, pipeline, {**plain, "consistency_scale": True}, kinds, None, 5.0, errors_after
    )
    assert errors_after[:2] == pytest.approx(errors_before[:2], rel=1e-12)  # same fixes, same RMSE
    assert errors_after[2] < errors_before[2]  # the papers' model is over-confident here: the scale grew

    def median_level(results: list) -> float:
        total = sum((r for r, _ in results[1:]), results[0][0])
        return float(total.summary(5.0)["median_protection_level_m"])

    assert median_level(after) > median_level(before)


def test_the_bound_widens_only_the_protection_level_and_grows_with_its_confidence() -> None:
    options = {"method": "gps_dr", **sim.PAPER_OPTIONS, "accel_std": 0.1, "integrity": True}
    point, truth = _drive({**options, "consistency_scale": True, "consistency_bound": False})
    bound, _ = _drive({**options, "consistency_scale": True})
    assert [(f.x, f.y, f.position_cov) for f in bound] == [(f.x, f.y, f.position_cov) for f in point]
    assert _figures(bound, truth)[0] == _figures(point, truth)[0]  # the covariance keeps the estimate
    assert sum(f.integrity == "ok" for f in point) > 0
    for p, b in zip(point, bound, strict=True):
        if b.protection_level is not None:
            assert p.protection_level is not None and b.protection_level > p.protection_level
    # a larger share of the risk for the scale: a lower confidence, a lower bound
    looser, _ = _drive({**options, "consistency_scale": True, "consistency_risk_share": 0.99})
    tighter, _ = _drive({**options, "consistency_scale": True, "consistency_risk_share": 0.01})
    pairs = [(a.protection_level, b.protection_level) for a, b in zip(looser, tighter, strict=True)]
    assert all(a < b for a, b in pairs if a is not None and b is not None)
    assert sum(a is not None for a, _ in pairs) >= sum(b is not None for _, b in pairs)


def test_the_bound_covers_the_misleading_epochs_of_the_estimate() -> None:
    # The papers' scene and model, a run (seed 1, run 3, straight, augUKF) where a protection level on the
    # noisy estimate is exceeded while ok: on the upper bound none is.
    run = sim.make_run(1, 3, "straight")
    pipeline = get_pipeline("v2v_coop")
    options = {**sim.PAPER_OPTIONS, "method": "aug_ukf", "integrity": True, "consistency_scale": True}

    def summary(extra: dict) -> dict:
        results = run_method(
            run, sim.VEHICLE_IDS, pipeline, {**options, **extra}, OWN | {"v2v_range"}, None, 5.0
        )
        return sum((r for r, _ in results[1:]), results[0][0]).summary(5.0)

    point, bound = summary({"consistency_bound": False}), summary({})
    assert point["misleading"] > 0 and bound["misleading"] == 0
    assert bound["availability"] <= point["availability"]


@pytest.mark.parametrize(
    ("module", "options"),
    [
        (v2v_coop, {"method": "aug_ukf", "consistency_scale": True}),
        (v2x_federated, {"consistency_scale": True}),
    ],
)
def test_the_scale_round_trips_and_an_old_state_decodes_without_one(module, options) -> None:
    # the pipeline itself, not the registry's (which wraps its state in the lag window)
    pipeline = v2v_coop.V2vCoopPipeline() if module is v2v_coop else v2x_federated.V2xFederatedPipeline()
    run = sim.make_run(0, 0, "straight")
    state = pipeline.create(pipeline.resolve_options(options), None)
    for k in range(12):
        batch = [o for o in run.observations[0][k] if o.kind in OWN]
        _, state = pipeline.process(state, batch, StaticEnvironment(vehicle_id="veh-1"))
    session = module._decode(state)
    assert session.consistency.t is not None and session.consistency.spread_square > 0.0
    assert module._decode(session.to_bytes()).consistency == session.consistency
    assert session.to_bytes() == state
    meta, arrays = state_format.unpack(state)
    assert len(meta["consistency"]) == 6
    three = dict(meta, consistency=meta["consistency"][:3], options=dict(meta["options"]))
    del three["options"]["consistency_bound"], three["options"]["consistency_risk_share"]
    before_bound = module._decode(state_format.pack(three, arrays))  # stored before the bound existed
    assert before_bound.consistency.estimate == session.consistency.estimate
    assert before_bound.options["consistency_scale"] is True
    assert before_bound.options["consistency_bound"] is False  # its protection level as it was
    del meta["consistency"]
    for name in ("consistency_scale", "consistency_time_constant_s"):
        del meta["options"][name]
    old = module._decode(state_format.pack(meta, arrays))  # as stored before the scale existed
    assert old.consistency == ConsistencyScale() and old.options["consistency_scale"] is False
    batch = [o for o in run.observations[0][12] if o.kind in OWN]
    fixes, _ = pipeline.process(old.to_bytes(), batch, StaticEnvironment(vehicle_id="veh-1"))
    assert fixes[-1].x is not None


@pytest.mark.parametrize("value", [0.5, 3601.0, "long"])
@pytest.mark.parametrize("name", ["v2v_coop", "v2x_federated"])
def test_the_time_constant_out_of_bounds_is_refused_by_field(name: str, value: object) -> None:
    with pytest.raises(PipelineInputError) as caught:
        get_pipeline(name).resolve_options({"consistency_time_constant_s": value})
    assert "consistency_time_constant_s" in str(caught.value.problems)


@pytest.mark.parametrize(
    ("option", "value"),
    [("consistency_risk_share", 0.0), ("consistency_risk_share", 1.0), ("consistency_risk_share", "half")],
)
@pytest.mark.parametrize("name", ["v2v_coop", "v2x_federated"])
def test_the_risk_share_out_of_bounds_is_refused_by_field(name: str, option: str, value: object) -> None:
    with pytest.raises(PipelineInputError) as caught:
        get_pipeline(name).resolve_options({option: value})
    assert option in str(caught.value.problems)


def test_federated_without_feedback_keeps_the_filters_protection_level() -> None:
    # Without feedback the fix's innovation tests the GPS sub-filter, not the fused fix: nothing measures
    # the fused fix's scale, and its protection level is the filter's (not unavailable for want of a bound).
    pipeline = v2x_federated.V2xFederatedPipeline()
    run = sim.make_run(0, 0, "straight")
    options = {"feedback": False, "integrity": True}
    levels = {}
    for scale in (False, True):
        state = pipeline.create(pipeline.resolve_options({**options, "consistency_scale": scale}), None)
        out = []
        for k in range(15):
            batch = [o for o in run.observations[0][k] if o.kind in OWN]
            fixes, state = pipeline.process(state, batch, StaticEnvironment(vehicle_id="veh-1"))
            out.append(fixes[-1].protection_level)
        levels[scale] = out
    assert levels[True] == levels[False] and levels[True][-1] is not None
