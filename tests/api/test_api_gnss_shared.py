"""The ephemerides are the site's, not a worker's: two apps on one shared store (two workers, or two
replicas) see the same file, and a batch on one worker uses the file uploaded through the other."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from apihelp import ADMIN, assert_error, make_settings
from edgepos.api.app import create_app
from edgepos.loadgen.localredis import RedisServer
from fastapi.testclient import TestClient
from gnsswire import QUICK, measurements, nav_text

TEXT = {**ADMIN, "Content-Type": "text/plain"}


@pytest.fixture(params=["sqlite", "redis"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'shared.db'}"
        return
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    with RedisServer(binary, tmp_path / "redis", "--save", "", "--appendonly", "no") as server:
        yield server.url("gnss:")


def _batch(client, session_id, token, seq, first):
    return client.post(
        f"/v1/sessions/{session_id}/batches",
        json={"seq": seq, "measurements": measurements(first, 1)},
        headers=token,
    )


def test_two_workers_share_the_ephemerides(tmp_path, store_url):
    settings = make_settings(tmp_path, store=store_url)
    with TestClient(create_app(settings)) as first, TestClient(create_app(settings)) as second:
        assert_error(second.get("/v1/ephemerides", headers=ADMIN), 404, "not_found")
        uploaded = first.put("/v1/ephemerides", content=nav_text(), headers=TEXT)
        assert uploaded.status_code == 200, uploaded.text
        assert second.get("/v1/ephemerides", headers=ADMIN).json() == uploaded.json()

        body = {"vehicle_id": "car", "pipeline": "gnss_tight", "options": QUICK}
        created = first.post("/v1/sessions", json=body, headers=ADMIN).json()
        session_id, token = created["session_id"], {"Authorization": f"Bearer {created['token']}"}
        response = _batch(second, session_id, token, 1, 0)  # parsed by the second worker from the store
        assert response.status_code == 200, response.text
        assert response.json()["fixes"][0]["status"] == "initialised"
        assert _batch(first, session_id, token, 2, 1).json()["fixes"][0]["status"] == "tracking"

        # Deleted through one worker: the other's cached copy is not used any more.
        assert first.delete("/v1/ephemerides", headers=ADMIN).status_code == 204
        assert_error(second.get("/v1/ephemerides", headers=ADMIN), 404, "not_found")
        error = assert_error(_batch(second, session_id, token, 3, 2), 422, "invalid_request")
        assert "no ephemerides are loaded" in error["message"]
        # Uploaded again through the other worker: back in use everywhere.
        assert second.put("/v1/ephemerides", content=nav_text(), headers=TEXT).status_code == 200
        assert _batch(first, session_id, token, 3, 2).status_code == 200


def test_each_worker_parses_a_file_once(tmp_path, monkeypatch):
    """Batches reuse the worker's parsed copy: the uploading worker never re-parses, another parses once."""
    import edgepos.api.ephemerides as ephemerides_module

    calls = []
    original = ephemerides_module.parse

    def counting(*args):
        calls.append(args[1])
        return original(*args)

    monkeypatch.setattr(ephemerides_module, "parse", counting)
    settings = make_settings(tmp_path, store=f"sqlite:///{tmp_path / 'parse.db'}")
    with TestClient(create_app(settings)) as first, TestClient(create_app(settings)) as second:
        digest = first.put("/v1/ephemerides", content=nav_text(), headers=TEXT).json()["digest"]
        body = {"vehicle_id": "car", "pipeline": "gnss_tight", "options": QUICK}
        for client in (first, first, second, second, second):
            created = client.post("/v1/sessions", json=body, headers=ADMIN).json()
            token = {"Authorization": f"Bearer {created['token']}"}
            for seq in (1, 2):
                assert _batch(client, created["session_id"], token, seq, seq - 1).status_code == 200
        assert second.get("/v1/ephemerides", headers=ADMIN).json()["digest"] == digest
    assert calls == [digest]  # the second worker's first batch; the first worker kept its upload's parse
