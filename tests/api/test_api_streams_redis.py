"""The fix stream through Redis: an app on a Redis store streams and resumes like the in-process one, and a
real ``edgepos serve --workers 2`` on a real loopback socket delivers every fix of batches spread over both
workers exactly once to one consumer (whichever worker serves it)."""

from __future__ import annotations

import itertools
from pathlib import Path

import httpx
import pytest
from apihelp import ADMIN, ADMIN_KEY, batch_body, make_settings, open_session, rsu_payload
from edgepos.api.app import create_app
from edgepos.loadgen.localredis import RedisServer
from edgepos.loadgen.localserver import clean_environment, running, serve_command
from fastapi.testclient import TestClient
from ssehelp import events, take, until_ping

STREAM = "/v1/stream/fixes"
_prefixes = itertools.count()


def test_stream_and_resume_on_redis(tmp_path: Path, redis_server: RedisServer):
    settings = make_settings(
        tmp_path, store=redis_server.url(f"streams{next(_prefixes)}:"), stream_ping_s=0.3, rate_limit_per_s=0
    )
    with TestClient(create_app(settings)) as client:
        assert client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
        session_id, auth = open_session(client)
        url = f"/v1/sessions/{session_id}/batches"
        with client.stream("GET", STREAM, headers=ADMIN) as response:
            stream = events(response.iter_lines())
            answer = client.post(url, json=batch_body(1, 0, 3), headers=auth).json()
            got = [e for e in take(stream, 3) if e.event == "fix"]
        assert [e.id for e in got] == ["1", "2", "3"]
        assert [e.json()["fix"] for e in got] == [{**fix, "state": None} for fix in answer["fixes"]]
        assert client.post(url, json=batch_body(2, 3, 2), headers=auth).status_code == 200
        with client.stream("GET", STREAM, headers={**ADMIN, "Last-Event-ID": "3"}) as response:
            stream = events(response.iter_lines())
            resumed = [e for e in take(stream, 2) if e.event == "fix"]
            assert until_ping(stream) == []
        assert [(e.id, e.json()["seq"]) for e in resumed] == [("4", 2), ("5", 2)]


@pytest.mark.slow
def test_two_workers_on_redis_deliver_every_fix_exactly_once(tmp_path: Path, redis_server: RedisServer):
    environment = clean_environment(
        EDGEPOS_STORE=redis_server.url(f"streams{next(_prefixes)}:"),
        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
        EDGEPOS_RATE_LIMIT_PER_S="0",
        EDGEPOS_STREAM_PING_S="0.5",
        EDGEPOS_LOG_LEVEL="warning",
    )
    with running(serve_command(2), environment, tmp_path / "server.log", ready_timeout_s=300.0) as base:
        assert httpx.put(f"{base}/v1/rsus", json=rsu_payload(), headers=ADMIN, timeout=30).status_code == 200
        sessions = []
        for vehicle in range(4):
            response = httpx.post(
                f"{base}/v1/sessions", json={"vehicle_id": f"car-{vehicle}"}, headers=ADMIN, timeout=30
            )
            assert response.status_code == 201, response.text
            created = response.json()
            sessions.append((created["session_id"], {"Authorization": f"Bearer {created['token']}"}))
        expected = set()
        with httpx.stream(
            "GET", f"{base}{STREAM}", headers=ADMIN, timeout=httpx.Timeout(60.0)
        ) as stream_response:
            assert stream_response.status_code == 200
            stream = events(stream_response.iter_lines())
            for seq in range(1, 6):
                for session_id, auth in sessions:
                    # a new connection per batch: the kernel hands connections to either worker
                    answer = httpx.post(
                        f"{base}/v1/sessions/{session_id}/batches",
                        json=batch_body(seq, 4 * (seq - 1), 4),
                        headers=auth,
                        timeout=30,
                    )
                    assert answer.status_code == 200, answer.text
                    expected |= {(session_id, seq, fix["t"]) for fix in answer.json()["fixes"]}
            got = [e for e in take(stream, len(expected), max_pings=60) if e.event == "fix"]
            extra = [e for e in until_ping(stream) if e.event == "fix"]
    assert len(expected) == 80
    assert extra == []
    assert len(got) == 80
    assert len({e.id for e in got}) == 80
    delivered = [(e.json()["session_id"], e.json()["seq"], e.json()["fix"]["t"]) for e in got]
    assert sorted(delivered) == sorted(expected)
