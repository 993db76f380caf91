"""EDGEPOS_REDIS_WAIT_REPLICAS at the service: with the replica down a batch is a 503 that says why and
is not acknowledged; the same batch sent again once the replica is back gets the answer the first
attempt stored (the batch was applied once)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest
from apihelp import ADMIN, assert_error, batch_body, make_settings, open_session, rsu_payload
from edgepos.api.app import create_app
from edgepos.loadgen.localredis import RedisServer
from fastapi.testclient import TestClient


def _link_up(primary: RedisServer, replica: RedisServer) -> None:
    deadline = time.monotonic() + 30.0
    while b"master_link_status:up" not in replica.command("INFO", "replication") or (
        b"connected_slaves:1" not in primary.command("INFO", "replication")
    ):
        assert time.monotonic() < deadline, "the replica did not connect"
        time.sleep(0.05)


def test_a_batch_the_replica_missed_is_a_503_and_its_retry_is_answered_once_replicated(tmp_path: Path):
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    primary = RedisServer(binary, tmp_path / "primary", "--save", "", "--appendonly", "no")
    primary.start()
    replica = RedisServer(
        binary,
        tmp_path / "replica",
        "--save",
        "",
        "--appendonly",
        "no",
        "--replicaof",
        "127.0.0.1",
        str(primary.port),
    )
    try:
        replica.start()
        _link_up(primary, replica)
        settings = make_settings(
            tmp_path,
            store=primary.url("api:"),
            redis_wait_replicas=1,
            redis_wait_timeout_ms=1500,  # the first batch's acknowledgement missed 300 ms once at load 4.7
            rate_limit_per_s=0,
        )
        with TestClient(create_app(settings)) as client:
            assert client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
            session_id, auth = open_session(client)
            url = f"/v1/sessions/{session_id}/batches"
            first = client.post(url, json=batch_body(1, 0, 5), headers=auth)
            assert first.status_code == 200, first.text

            replica.stop()
            refused = client.post(url, json=batch_body(2, 5, 5), headers=auth)
            error = assert_error(refused, 503, "unavailable")
            assert (
                "reached 0 of the 1 replica(s)" in error["message"]
                and "send the same batch again" in error["message"]
            )
            assert str(primary.port) not in error["message"]
            assert int(refused.headers["Retry-After"]) >= 1
            assert_error(
                client.post(url, json=batch_body(2, 5, 5), headers=auth), 503, "unavailable"
            )  # still not

            replica.start()
            _link_up(primary, replica)
            retried = client.post(url, json=batch_body(2, 5, 5), headers=auth)
            assert retried.status_code == 200, retried.text
            session = client.get(f"/v1/sessions/{session_id}", headers=auth).json()
            assert (session["last_seq"], session["batches"], session["epochs"]) == (2, 2, 10)  # applied once
    finally:
        replica.stop()
        primary.stop()
