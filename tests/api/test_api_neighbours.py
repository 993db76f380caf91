"""Cooperation across sessions through the API: a v2v range reads the peer's position from the
peer's own session, and two vehicles ranging to each other while both update at once never
deadlock, never see a half-written track and lose no batch."""

from __future__ import annotations

import asyncio
import math
import threading
from typing import Any

from apihelp import batch_body, open_session
from edgepos.pipelines.tracks import TRACK_HISTORY_POINTS

STEP = 0.2
BATCHES = 25
#: Bound on one epoch of both vehicles (two batches): a deadlocked service fails the test, never hangs it.
EPOCH_TIMEOUT_S = 60.0


def batch(vehicle_y: float, peer: str, k: int) -> list[dict]:
    """One epoch of a vehicle driving east at 10 m/s on the line y = vehicle_y, ranging to ``peer``
    on the other lane (4 m away, level with it)."""
    t = round(k * STEP, 6)
    return [
        {"type": "gnss_fix", "t": t, "x": 10.0 * t, "y": vehicle_y, "std": 1.0},
        {"type": "gyro", "t": t, "yaw_rate": 0.0},
        {"type": "odometer", "t": t, "speed": 10.0},
        {"type": "v2v_range", "t": t, "peer_vehicle_id": peer, "range": 4.0},
    ]


def test_a_range_uses_the_peer_session_and_says_when_it_cannot(client):
    # Taken as independent, a found peer's range is always used (by covariance intersection, the default,
    # a peer no better placed than the vehicle gets no weight): what is checked here is the plumbing.
    lone, lone_auth = open_session(
        client, vehicle_id="lone", pipeline="v2x_federated", options={"neighbour_fusion": "independent"}
    )
    response = client.post(
        f"/v1/sessions/{lone}/batches",
        json={"seq": 1, "measurements": batch(0.0, "ghost", 0) + batch(0.0, "lone", 1)},
        headers=lone_auth,
    )
    assert response.status_code == 200, response.text
    reasons = [
        u["reason"] for f in response.json()["fixes"] for u in f["measurements"] if u["type"] == "v2v_range"
    ]
    assert any("initialised" in r or "first gnss_fix" in r for r in reasons if r)
    assert any(r and "itself" in r for r in reasons), reasons
    peer, peer_auth = open_session(client, vehicle_id="peer", pipeline="v2x_federated")
    assert (
        client.post(
            f"/v1/sessions/{peer}/batches",
            json={"seq": 1, "measurements": batch(4.0, "x", 2)[:3]},
            headers=peer_auth,
        ).status_code
        == 200
    )
    response = client.post(
        f"/v1/sessions/{lone}/batches",
        json={"seq": 2, "measurements": batch(0.0, "peer", 2)},
        headers=lone_auth,
    )
    used = [u for f in response.json()["fixes"] for u in f["measurements"] if u["type"] == "v2v_range"]
    assert used and all(u["used"] for u in used), used


def test_two_vehicles_ranging_to_each_other_update_concurrently(client):
    """Two vehicles on neighbouring lanes range to each other while both stream their batches.

    They advance in lockstep: a barrier per epoch releases both threads at once, so the two batches of
    epoch k race each other through the service (which one is applied first is up to the scheduler),
    but neither vehicle ever gets a whole epoch ahead of the other. So the expectations hold whatever
    the machine's load: when epoch k >= 1 starts, both batches of epoch k-1 are applied and published,
    and a range of epoch k finds the peer's track ending at t_k (the peer's batch went first) or at
    t_{k-1}, one step back. ``max_neighbour_age`` is 1.5 steps, so every such range must be used; a
    track the service dropped, wrote out of order or mixed up with the vehicle's own shows up as an
    unused range or a gap in the published history. Without the lockstep the two threads drift apart
    on a busy machine by more than any max_neighbour_age, which is the service working as documented.
    """
    lanes = {"north": (4.0, "south"), "south": (0.0, "north")}
    options = {"max_neighbour_age": 1.5 * STEP, "neighbour_fusion": "independent"}  # every found range used
    sessions = {
        name: open_session(client, vehicle_id=name, pipeline="v2x_federated", options=options)
        for name in lanes
    }
    # The two vehicles and this thread, the referee: every epoch starts when all three arrive, and
    # one that waits longer than EPOCH_TIMEOUT_S breaks the barrier for all (a hang becomes a failure).
    barrier = threading.Barrier(len(lanes) + 1, timeout=EPOCH_TIMEOUT_S)
    replies: dict[str, list[tuple[int, Any]]] = {name: [] for name in lanes}
    failures: dict[str, str] = {}

    def drive(name: str) -> None:
        session_id, auth = sessions[name]
        y, peer = lanes[name]
        try:
            for k in range(BATCHES):
                barrier.wait()  # epoch k starts for both vehicles at the same moment
                body = {"seq": k + 1, "measurements": batch(y, peer, k)}
                response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=auth)
                ok = response.status_code == 200
                replies[name].append((response.status_code, response.json() if ok else response.text))
                if not ok:
                    raise AssertionError(f"epoch {k}: {response.status_code} {response.text}")
            barrier.wait()  # the end of the last epoch
        except BaseException as error:  # noqa: BLE001 - whatever a lane raises is reported by the main thread
            failures[name] = f"{type(error).__name__}: {error}"
            barrier.abort()  # the others stop now instead of waiting out the timeout

    threads = [threading.Thread(target=drive, args=(name,), daemon=True) for name in lanes]
    for thread in threads:
        thread.start()
    try:
        for _ in range(BATCHES + 1):  # the start of every epoch, then the end of the last one
            barrier.wait()
    except threading.BrokenBarrierError:
        barrier.abort()  # a vehicle failed (its error is in failures) or one never came back
    for thread in threads:
        thread.join(EPOCH_TIMEOUT_S)
    stuck = [name for name, thread in zip(lanes, threads) if thread.is_alive()]
    assert stuck == [], f"{stuck}: a request never returned within {EPOCH_TIMEOUT_S} s (deadlock?)"
    assert failures == {}, failures

    times = [round(k * STEP, 6) for k in range(BATCHES)]
    for name, (session_id, auth) in sessions.items():
        assert [status for status, _ in replies[name]] == [200] * BATCHES
        fixes = [fix for _, body in replies[name] for fix in body["fixes"]]
        # Every batch applied exactly once and in order: one fix per epoch, at that epoch's time.
        assert [fix["t"] for fix in fixes] == times
        state = client.get(f"/v1/sessions/{session_id}", headers=auth).json()
        assert (state["last_seq"], state["batches"], state["epochs"]) == (BATCHES, BATCHES, BATCHES)
        assert all(math.isfinite(f["x"]) and math.isfinite(f["y"]) for f in fixes)
        ranges = [[u for u in fix["measurements"] if u["type"] == "v2v_range"] for fix in fixes]
        assert all(len(found) == 1 for found in ranges)
        # Epoch 0 starts the session from its gnss_fix, so its range says why it was not used; from
        # epoch 1 on every range used the peer's track, at most one step old.
        assert not ranges[0][0]["used"] and ranges[0][0]["reason"]
        unused = [(k, found[0]["reason"]) for k, found in enumerate(ranges) if k and not found[0]["used"]]
        assert unused == [], unused[:3]
        y = lanes[name][0]
        assert abs(fixes[-1]["y"] - y) < 1.5 and abs(fixes[-1]["x"] - 10.0 * times[-1]) < 3.0

    # Nothing was lost from the published tracks either: each holds its vehicle's latest estimates,
    # one per epoch without a gap, on its own lane.
    published = asyncio.run(client.app.state.context.store.get_tracks(list(lanes)))
    for name, (y, _) in lanes.items():
        points = published[name].points
        assert published[name].vehicle_id == name
        assert [p.t for p in points] == times[-TRACK_HISTORY_POINTS:]
        assert all(abs(p.y - y) < 1.5 for p in points), [p.y for p in points]


def test_sessions_of_non_cooperative_pipelines_publish_no_track(client):
    plain, plain_auth = open_session(client, vehicle_id="plain", pipeline="rsu_imu")
    response = client.post(f"/v1/sessions/{plain}/batches", json=batch_body(1, 0, 5), headers=plain_auth)
    assert response.status_code == 200, response.text
    store = client.app.state.context.store
    assert asyncio.run(store.get_tracks(["plain"])) == {}
    coop, coop_auth = open_session(client, vehicle_id="coop", pipeline="v2x_federated")
    response = client.post(
        f"/v1/sessions/{coop}/batches",
        json={"seq": 1, "measurements": batch(0.0, "plain", 0) + batch(0.0, "plain", 1)},
        headers=coop_auth,
    )
    reasons = [u["reason"] for u in response.json()["fixes"][1]["measurements"] if u["type"] == "v2v_range"]
    assert reasons and "cooperative pipeline" in reasons[0], reasons
    assert asyncio.run(store.get_tracks(["coop"]))["coop"].points[-1].t == 0.2
