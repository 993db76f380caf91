"""Cooperation across sessions through the API: a v2v range reads the peer's position from the
peer's own session, and two vehicles ranging to each other while both update at once never
deadlock, never see a half-written track and lose no batch."""

from __future__ import annotations

import asyncio
import math
from concurrent.futures import ThreadPoolExecutor

from apihelp import batch_body, open_session

STEP = 0.2
BATCHES = 25


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
    lone, lone_auth = open_session(client, vehicle_id="lone", pipeline="v2x_federated")
    response = client.post(f"/v1/sessions/{lone}/batches", json={"seq": 1, "measurements": batch(0.0, "ghost", 0) + batch(0.0, "lone", 1)}, headers=lone_auth)
    assert response.status_code == 200, response.text
    reasons = [u["reason"] for f in response.json()["fixes"] for u in f["measurements"] if u["type"] == "v2v_range"]
    assert any("initialised" in r or "first gnss_fix" in r for r in reasons if r)
    assert any(r and "itself" in r for r in reasons), reasons
    peer, peer_auth = open_session(client, vehicle_id="peer", pipeline="v2x_federated")
    assert client.post(f"/v1/sessions/{peer}/batches", json={"seq": 1, "measurements": batch(4.0, "x", 2)[:3]}, headers=peer_auth).status_code == 200
    response = client.post(f"/v1/sessions/{lone}/batches", json={"seq": 2, "measurements": batch(0.0, "peer", 2)}, headers=lone_auth)
    used = [u for f in response.json()["fixes"] for u in f["measurements"] if u["type"] == "v2v_range"]
    assert used and all(u["used"] for u in used), used


def test_two_vehicles_ranging_to_each_other_update_concurrently(client):
    sessions = {name: open_session(client, vehicle_id=name, pipeline="v2x_federated") for name in ("north", "south")}
    lanes = {"north": (4.0, "south"), "south": (0.0, "north")}

    def drive(name: str) -> list[dict]:
        session_id, auth = sessions[name]
        y, peer = lanes[name]
        fixes = []
        for k in range(BATCHES):
            response = client.post(
                f"/v1/sessions/{session_id}/batches", json={"seq": k + 1, "measurements": batch(y, peer, k)}, headers=auth
            )
            assert response.status_code == 200, response.text
            fixes.extend(response.json()["fixes"])
        return fixes

    with ThreadPoolExecutor(max_workers=2) as pool:
        results = dict(zip(("north", "south"), pool.map(drive, ("north", "south"))))
    for name, fixes in results.items():
        session_id, auth = sessions[name]
        state = client.get(f"/v1/sessions/{session_id}", headers=auth).json()
        assert state["last_seq"] == BATCHES and state["epochs"] == BATCHES
        assert all(math.isfinite(f["x"]) and math.isfinite(f["y"]) for f in fixes)
        ranges = [u for f in fixes[2:] for u in f["measurements"] if u["type"] == "v2v_range"]
        # Each range either used the peer's track or says exactly why not (never a 500, never NaN).
        assert all(u["used"] or u["reason"] for u in ranges)
        assert sum(u["used"] for u in ranges) >= BATCHES // 2, [u["reason"] for u in ranges if not u["used"]][:3]
        y = lanes[name][0]
        assert abs(fixes[-1]["y"] - y) < 1.5 and abs(fixes[-1]["x"] - 10.0 * (BATCHES - 1) * STEP) < 3.0


def test_sessions_of_non_cooperative_pipelines_publish_no_track(client):
    plain, plain_auth = open_session(client, vehicle_id="plain", pipeline="rsu_imu")
    response = client.post(f"/v1/sessions/{plain}/batches", json=batch_body(1, 0, 5), headers=plain_auth)
    assert response.status_code == 200, response.text
    store = client.app.state.context.store
    assert asyncio.run(store.get_tracks(["plain"])) == {}
    coop, coop_auth = open_session(client, vehicle_id="coop", pipeline="v2x_federated")
    response = client.post(f"/v1/sessions/{coop}/batches", json={"seq": 1, "measurements": batch(0.0, "plain", 0) + batch(0.0, "plain", 1)}, headers=coop_auth)
    reasons = [u["reason"] for u in response.json()["fixes"][1]["measurements"] if u["type"] == "v2v_range"]
    assert reasons and "cooperative pipeline" in reasons[0], reasons
    assert asyncio.run(store.get_tracks(["coop"]))["coop"].points[-1].t == 0.2
