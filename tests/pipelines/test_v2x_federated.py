"""The federated GPS/DR/V2X filter: square-root UKF against the UKF, eq. 15 against the
information-weighted mean, the odometer model against finite differences, state round trips,
per-measurement reasons and the paper's orderings on a few runs."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.filters import make_filter
from edgepos.core.filters.srukf import SquareRootUnscentedKalmanFilter, cholesky_update
from edgepos.core.filters.ukf import UnscentedKalmanFilter
from edgepos.core.measurements.odometer import OdometerDistance, dead_reckoning
from edgepos.core.motion.ct import CoordinatedTurn
from edgepos.core.motion.current_statistical import CurrentStatistical
from edgepos.core.observations import (
    GnssFixObservation,
    GyroObservation,
    OdometerObservation,
    V2vRangeObservation,
)
from edgepos.eval.federated import METHODS, assisting_tracks, run_method
from edgepos.pipelines.base import (
    InitialState,
    NeighbourTrack,
    PipelineInputError,
    StaticEnvironment,
    TrackPoint,
)
from edgepos.pipelines.registry import get_pipeline
from edgepos.pipelines.v2x_federated import RangesToPoints, fuse
from edgepos.sim.federated import make_run

KIN = layout.KINEMATIC


def _gaussian(seed: int, dim: int = 6) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(dim, dim))
    mean = np.array([3.0, 10.0, 0.2, -4.0, 1.0, 0.1][:dim]) + rng.normal(size=dim)
    return mean, a @ a.T + 0.5 * np.eye(dim)


@pytest.mark.parametrize("alpha", [1.0, 0.5])  # 0.5: negative centre covariance weight (downdate)
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_square_root_ukf_equals_ukf(alpha, seed):
    mean, cov = _gaussian(seed)
    root, plain = SquareRootUnscentedKalmanFilter(alpha=alpha), UnscentedKalmanFilter(alpha=alpha)
    motion = CurrentStatistical(0.1, 10.0)
    for filt_out in ((root.predict(mean, cov, motion, 0.2), plain.predict(mean, cov, motion, 0.2)),):
        np.testing.assert_allclose(filt_out[0][0], filt_out[1][0], atol=1e-9)
        np.testing.assert_allclose(filt_out[0][1], filt_out[1][1], atol=1e-9)
    ranges = RangesToPoints(np.array([[30.0, 5.0], [-20.0, -4.0], [10.0, 40.0]]), np.array([9.0, 9.0, 4.0]))
    for model, z in ((dead_reckoning(0.005, 0.1, 0.2), [0.01, 2.1]), (ranges, [28.0, 24.0, 45.0])):
        a = root.update_one(mean, cov, KIN, model, np.array(z))
        b = plain.update_one(mean, cov, KIN, model, np.array(z))
        for x, y in zip(a, b):
            np.testing.assert_allclose(x, y, atol=1e-9, rtol=1e-9)


def test_square_root_ukf_equals_ukf_through_a_nonlinear_motion():
    mean8 = np.array([1.0, 8.0, 0.3, 2.0, 3.0, -0.2, 0.4, 0.1])
    rng = np.random.default_rng(5)
    a = rng.normal(size=(8, 8)) * 0.3
    cov8 = a @ a.T + 0.1 * np.eye(8)
    motion = CoordinatedTurn()
    idx = list(motion.components)
    mean, cov = mean8[idx], cov8[np.ix_(idx, idx)]
    a_mean, a_cov = SquareRootUnscentedKalmanFilter().predict(mean, cov, motion, 0.2)
    b_mean, b_cov = UnscentedKalmanFilter().predict(mean, cov, motion, 0.2)
    np.testing.assert_allclose(a_mean, b_mean, atol=1e-9)
    np.testing.assert_allclose(a_cov, b_cov, atol=1e-9)


def test_srukf_is_registered():
    assert isinstance(make_filter("srukf"), SquareRootUnscentedKalmanFilter)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_cholesky_update_against_the_matrix(sign):
    _, cov = _gaussian(4)
    upper = np.linalg.cholesky(cov).T
    v = np.array([0.3, -0.2, 0.1, 0.05, 0.4, -0.1])
    updated = cholesky_update(upper, v, sign)
    np.testing.assert_allclose(updated.T @ updated, cov + sign * np.outer(v, v), atol=1e-12)


def test_eq15_is_the_information_weighted_mean():
    mean_a, cov_a = _gaussian(7)
    mean_b, cov_b = _gaussian(8)
    mean, cov = fuse(mean_a, cov_a, mean_b, cov_b)
    info = np.linalg.inv(cov_a) + np.linalg.inv(cov_b)
    np.testing.assert_allclose(cov, np.linalg.inv(info), rtol=1e-9, atol=1e-12)
    expected = np.linalg.solve(info, np.linalg.solve(cov_a, mean_a) + np.linalg.solve(cov_b, mean_b))
    np.testing.assert_allclose(mean, expected, rtol=1e-9, atol=1e-12)
    # Two equal estimates fuse to the same mean with half the covariance.
    mean, cov = fuse(mean_a, cov_a, mean_a, cov_a)
    np.testing.assert_allclose(mean, mean_a, atol=1e-12)
    np.testing.assert_allclose(cov, cov_a / 2, rtol=1e-9)


def test_eq15_refuses_an_indefinite_covariance():
    from edgepos.core.errors import NumericalError

    mean, cov = _gaussian(1)
    with pytest.raises(NumericalError):
        fuse(mean, cov, mean, -cov)


@pytest.mark.parametrize(
    "model",
    [
        OdometerDistance(0.1, 0.2),
        dead_reckoning(0.005, 0.1, 0.2),
        RangesToPoints(np.array([[30.0, 5.0], [-3.0, 8.0]]), np.ones(2)),
    ],
)
def test_dr_and_range_jacobians_against_finite_differences(model):
    rng = np.random.default_rng(3)
    for _ in range(5):
        state = rng.normal(size=layout.FULL_DIM) * 5 + np.array([0, 10, 0, 0, 2, 0, 0, 0])
        jac = model.jacobian(state[None])[0]
        numeric = np.zeros_like(jac)
        for j in range(layout.FULL_DIM):
            step = np.zeros(layout.FULL_DIM)
            step[j] = 1e-6
            numeric[:, j] = (
                model.predict((state + step)[None])[0] - model.predict((state - step)[None])[0]
            ) / 2e-6
        np.testing.assert_allclose(jac, numeric, atol=1e-6, rtol=1e-6)


def test_odometer_prediction_is_interval_times_speed():
    state = np.zeros((1, layout.FULL_DIM))
    state[0, layout.XV], state[0, layout.YV] = 3.0, 4.0
    assert OdometerDistance(0.1, 0.2).predict(state)[0, 0] == pytest.approx(1.0)


def _session(**options):
    pipeline = get_pipeline("v2x_federated")
    return pipeline, pipeline.create(pipeline.resolve_options(options), None)


def test_state_round_trips_bit_for_bit_and_processing_is_pure():
    pipeline, state = _session()
    run = make_run(3, 0, "clean", steps=6)
    for epoch, tracks in zip(run.observations, assisting_tracks(run)):
        env = StaticEnvironment(tracks=tracks, vehicle_id="target")
        before = bytes(state)
        fixes, new_state = pipeline.process(state, epoch, env)
        assert state == before
        again, again_state = pipeline.process(before, epoch, env)
        assert again_state == new_state and again == fixes
        state = new_state
    assert fixes[-1].status == "tracking"
    assert all(use.used for use in fixes[-1].measurements)


def test_fix_says_why_measurements_were_not_used():
    pipeline, state = _session()
    fixes, state = pipeline.process(state, [GyroObservation(0.0, 0.0)], StaticEnvironment())
    assert fixes[0].status == "uninitialised" and "gnss_fix" in fixes[0].measurements[0].reason
    batch = [GnssFixObservation(0.2, 1.0, 2.0), OdometerObservation(0.2, distance=2.0)]
    fixes, state = pipeline.process(state, batch, StaticEnvironment())
    assert fixes[0].status == "initialised"
    own = NeighbourTrack(
        "me", (TrackPoint(0.4, 0.0, 0.0, 0.0, 0.0, tuple(tuple(r) for r in np.eye(4).tolist())),)
    )
    env = StaticEnvironment(tracks={"me": own}, vehicle_id="me")
    batch = [
        OdometerObservation(0.4, distance=2.0),
        V2vRangeObservation(0.4, "ghost", range=10.0),
        V2vRangeObservation(0.4, "me", range=10.0),
        GnssFixObservation(0.4, 3.0, 2.0),
    ]
    fixes, state = pipeline.process(state, batch, env)
    uses = fixes[0].measurements
    assert [u.used for u in uses] == [True, False, False, True]
    assert "no live session" in uses[1].reason and "itself" in uses[2].reason


def test_first_odometer_distance_has_no_interval():
    pipeline = get_pipeline("v2x_federated")
    # Started with a velocity, its first fix lets dead reckoning start (from rest it waits for a second).
    state = pipeline.create(pipeline.resolve_options({}), InitialState(0.0, 0.0, 10.0, 0.0))
    batch = [GnssFixObservation(0.0, 0.0, 0.0)]
    _, state = pipeline.process(state, batch, StaticEnvironment())
    fixes, _ = pipeline.process(state, [OdometerObservation(0.2, distance=2.0)], StaticEnvironment())
    assert not fixes[0].measurements[0].used and "first distance" in fixes[0].measurements[0].reason


def test_time_going_back_beyond_the_window_is_reported_with_the_session_untouched():
    """Older than the lag window (max_delay_s 1 s): not used, said so in the session's newest fix, and a
    batch of nothing else leaves the state as it was; a malformed one still refuses the batch, naming its
    field. Inside the window a measurement is filtered at its time, and a batch out of time order is the
    batch in time order (this pipeline once refused both)."""
    pipeline, state = _session()
    environment = StaticEnvironment()
    first = [GnssFixObservation(t, t, 0.0) for t in (1.0, 1.5, 2.0, 2.5, 3.0)]
    _, state = pipeline.process(state, first, environment)
    fixes, after = pipeline.process(state, [GnssFixObservation(0.5, 0.0, 0.0)], environment)
    assert after == state
    assert [(f.t, f.revised) for f in fixes] == [(3.0, True)]
    [use] = fixes[0].measurements
    assert (use.index, use.used) == (0, False) and use.reason.startswith("too late: t=0.5 is 2.5 s older")
    with pytest.raises(PipelineInputError) as error:
        malformed = [OdometerObservation(0.5, distance=-1.0), GnssFixObservation(3.5, 3.5, 0.0)]
        pipeline.process(state, malformed, environment)
    assert [(p.index, p.field) for p in error.value.problems] == [(0, "distance")]
    in_order = [GnssFixObservation(2.7, 2.7, 0.0), GnssFixObservation(3.5, 3.5, 0.0)]
    fixes_in_order, state_in_order = pipeline.process(state, in_order, environment)
    fixes_backwards, state_backwards = pipeline.process(state, in_order[::-1], environment)
    assert state_backwards == state_in_order
    assert [(f.t, f.revised) for f in fixes_backwards] == [(2.7, False), (3.0, True), (3.5, False)]
    assert [(f.x, f.vx) for f in fixes_backwards] == [(f.x, f.vx) for f in fixes_in_order]


def test_orderings_on_a_few_runs():
    """Each added source helps and feedback beats none, on the sum of three runs per scenario."""
    for scenario in ("clean", "multipath"):
        totals = dict.fromkeys(METHODS, 0.0)
        for r in range(3):
            run = make_run(11, r, scenario, steps=150)
            for method in METHODS:
                totals[method] += float(run_method(run, method)[0][1:].sum())
        assert totals["GPS"] > totals["GPS/DR"] > totals["GPS/DR/V2X"], (scenario, totals)
        assert totals["GPS/DR/V2X-nofeedback"] > totals["GPS/DR/V2X"], (scenario, totals)
