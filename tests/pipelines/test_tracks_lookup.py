"""Neighbour look-up (pipelines/tracks.py): what a session publishes and how a peer's position at a
measurement time is read back — inside the history, predicted forward, or refused with a reason
(no session, stale, the vehicle itself, older than the history)."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.pipelines.base import Fix, NeighbourTrack, TrackPoint
from edgepos.pipelines.tracks import NeighbourUnavailable, position_at, publish

COV = tuple(tuple(float(i == j) * (1.0 + i) for j in range(4)) for i in range(4))


def point(t: float, x: float, y: float = 0.0, vx: float = 10.0, vy: float = 0.0) -> TrackPoint:
    return TrackPoint(t, x, y, vx, vy, COV)


def fix(t: float, x: float) -> Fix:
    return Fix(t=t, status="tracking", x=x, y=0.0, vx=10.0, vy=0.0, kinematic_cov=[list(row) for row in COV])


TRACK = NeighbourTrack("peer", (point(1.0, 10.0), point(1.2, 12.0), point(1.4, 14.0)))


def test_at_a_published_point_the_estimate_is_exact():
    got = position_at(TRACK, 1.2, max_age=1.0, accel_std=1.0)
    assert got.source == "history"
    np.testing.assert_array_equal(got.position, [12.0, 0.0])
    np.testing.assert_array_equal(got.cov, np.array(COV)[:2, :2])


def test_an_older_measurement_is_interpolated_inside_the_history():
    got = position_at(TRACK, 1.05, max_age=1.0, accel_std=1.0)
    assert got.source == "history"
    np.testing.assert_allclose(got.position, [10.5, 0.0], rtol=0, atol=1e-12)


def test_a_newer_measurement_is_predicted_forward_with_grown_covariance():
    got = position_at(TRACK, 1.9, max_age=1.0, accel_std=2.0)
    assert got.source == "predicted"
    np.testing.assert_allclose(got.position, [19.0, 0.0], atol=1e-12)
    dt = 0.5
    transition = np.array([[1.0, 0.0, dt, 0.0], [0.0, 1.0, 0.0, dt]])
    expected = transition @ np.array(COV) @ transition.T + np.eye(2) * 4.0 * dt**4 / 4.0
    np.testing.assert_allclose(got.cov, expected, rtol=1e-12)
    assert np.all(np.linalg.eigvalsh(got.cov) > 0)


@pytest.mark.parametrize(
    "track,t,self_id,words",
    [
        (None, 1.2, None, "no live session"),
        (TRACK, 2.5, None, "older than the measurement"),  # stale: 1.1 s past the last point
        (TRACK, 1.2, "peer", "this vehicle itself"),
        (TRACK, 0.5, None, "older than the peer's published history"),
        (NeighbourTrack("peer", ()), 1.2, None, "published no estimate"),
    ],
)
def test_unusable_neighbours_are_refused_with_the_reason(track, t, self_id, words):
    with pytest.raises(NeighbourUnavailable, match=words):
        position_at(track, t, max_age=1.0, accel_std=1.0, self_id=self_id)


def test_the_vehicle_itself_is_refused_even_before_it_has_published():
    with pytest.raises(NeighbourUnavailable, match="itself"):
        position_at(None, 1.2, max_age=1.0, accel_std=1.0, self_id="me", peer_id="me")


def test_publish_keeps_older_points_replaces_overlap_and_bounds_the_history():
    first = publish("peer", None, [fix(0.2 * k, 2.0 * k) for k in range(5)])
    assert [p.t for p in first.points] == [0.2 * k for k in range(5)]
    # A batch that starts inside the history replaces the overlapping points (a replayed or
    # re-filtered stretch), keeps the older ones.
    second = publish("peer", first, [fix(0.6, 99.0), fix(1.0, 100.0)])
    assert [p.t for p in second.points] == [0.0, 0.2, 0.4, 0.6, 1.0]
    assert second.points[3].x == 99.0
    bounded = publish("peer", second, [fix(2.0 + 0.2 * k, 0.0) for k in range(30)], keep=20)
    assert len(bounded.points) == 20 and bounded.points[-1].t == pytest.approx(2.0 + 0.2 * 29)


def test_a_batch_without_a_kinematic_fix_publishes_nothing():
    assert publish("peer", TRACK, [Fix(t=3.0, status="uninitialised")]) is None
