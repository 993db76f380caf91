"""Two app instances (as two workers would be) sharing one SQLite file: a session's batches are
applied exactly once, whichever instance gets them."""

from __future__ import annotations

import threading

from apifakes import GatedPipeline
from apihelp import ADMIN, batch_body, make_settings, rsu_payload
from edgepos.api.app import create_app
from edgepos.pipelines.lag import LagWindow
from edgepos.pipelines.plausibility import Plausible
from fastapi.testclient import TestClient


def test_racing_instances_apply_a_batch_once(tmp_path):
    url = f"sqlite:///{tmp_path / 'shared.db'}"
    slow = GatedPipeline()
    # wrapped as the registry wraps every pipeline (lag window around plausibility), so that both instances
    # read the same state format: B creates the session, and A must be able to read it
    app_a = create_app(make_settings(tmp_path, store=url), pipelines={"rsu_imu": LagWindow(Plausible(slow))})
    app_b = create_app(make_settings(tmp_path, store=url))
    with TestClient(app_a) as a, TestClient(app_b) as b:
        a.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        created = b.post("/v1/sessions", json={"vehicle_id": "car"}, headers=ADMIN).json()
        session_id, token = created["session_id"], {"Authorization": f"Bearer {created['token']}"}
        path = f"/v1/sessions/{session_id}/batches"
        body = batch_body(1, 0, 4)
        slow.gate = threading.Event()
        answers = {}
        worker_a = threading.Thread(
            target=lambda: answers.setdefault("a", a.post(path, json=body, headers=token))
        )
        worker_a.start()
        assert slow.entered.wait(10.0)  # A loaded version 0 and is filtering
        answers["b"] = b.post(path, json=body, headers=token)  # B applies the same batch first
        assert answers["b"].status_code == 200
        slow.gate.set()
        worker_a.join(20.0)
        assert answers["a"].status_code == 200
        assert answers["a"].content == answers["b"].content  # A lost the compare-and-set and replayed
        info = a.get(f"/v1/sessions/{session_id}", headers=token).json()
        assert (info["last_seq"], info["batches"], info["epochs"]) == (1, 1, 4)
        assert "edgepos_store_conflicts_total 1.0" in a.get("/metrics").text
        assert b.post(path, json=batch_body(2, 4, 4), headers=token).status_code == 200
        assert a.get(f"/v1/sessions/{session_id}", headers=token).json()["epochs"] == 8


def test_concurrent_batches_through_two_instances(tmp_path):
    url = f"sqlite:///{tmp_path / 'shared.db'}"
    with (
        TestClient(create_app(make_settings(tmp_path, store=url))) as a,
        TestClient(create_app(make_settings(tmp_path, store=url))) as b,
    ):
        a.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        sessions = []
        for index in range(2):
            created = (
                (a if index == 0 else b)
                .post("/v1/sessions", json={"vehicle_id": f"car-{index}"}, headers=ADMIN)
                .json()
            )
            sessions.append((created["session_id"], {"Authorization": f"Bearer {created['token']}"}))
        errors: list[str] = []

        def drive(session_id: str, token: dict[str, str], offset: int) -> None:
            for seq in range(1, 9):
                client = (a, b)[(seq + offset) % 2]
                response = client.post(
                    f"/v1/sessions/{session_id}/batches",
                    json=batch_body(seq, 2 * seq + offset, 2),
                    headers=token,
                )
                if response.status_code != 200:
                    errors.append(response.text)

        # each session alternates between the instances; the two sessions run at the same time
        threads = [
            threading.Thread(target=drive, args=(*sessions[0], 0)),
            threading.Thread(target=drive, args=(*sessions[1], 1)),
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60.0)
        assert errors == []
        for session_id, token in sessions:
            info = b.get(f"/v1/sessions/{session_id}", headers=token).json()
            assert (info["last_seq"], info["batches"], info["epochs"]) == (8, 8, 16)
