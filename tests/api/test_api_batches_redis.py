"""Batches through two apps on one Redis, as two workers serve them: each worker applies a batch on the
record it wrote last (one round trip, store.redis_cache) only while that is the stored version. Batches
alternating between the workers are all applied in seq order and answered as one worker would; a session
deleted, superseded or revoked through one worker refuses the next batch sent to the other at once."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
from apihelp import ADMIN, assert_error, batch_body, bearer, make_settings, open_session, rsu_payload
from edgepos.api.app import create_app
from edgepos.loadgen.localredis import RedisServer
from fastapi.testclient import TestClient

_prefixes = itertools.count()


@pytest.fixture
def two_workers(tmp_path: Path, redis_server: RedisServer) -> Iterator[tuple[TestClient, TestClient]]:
    """Two apps (two workers' stores and caches) on one Redis prefix, the paper's RSUs loaded."""
    url = redis_server.url(f"batches{next(_prefixes)}:")
    with ExitStack() as stack:
        clients = [
            stack.enter_context(
                TestClient(create_app(make_settings(tmp_path / name, store=url, rate_limit_per_s=0)))
            )
            for name in ("a", "b")
        ]
        assert clients[0].put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
        yield clients[0], clients[1]


def test_batches_alternating_between_workers_are_each_applied_once(two_workers):
    first, second = two_workers
    session_id, token = open_session(first)
    url = f"/v1/sessions/{session_id}/batches"
    answers = []
    for seq, worker in enumerate([first, first, second, first, second, second, first], start=1):
        response = worker.post(url, json=batch_body(seq, 3 * (seq - 1), 3), headers=token)
        assert response.status_code == 200, response.text
        answers.append(response.json())
    # the last batch again through the worker that did not apply it: the stored answer, not a second write
    replay = second.post(url, json=batch_body(7, 18, 3), headers=token)
    assert replay.status_code == 200 and replay.json() == answers[-1]
    stale = second.post(url, json=batch_body(6, 15, 3), headers=token)
    assert_error(stale, 409, "conflict")
    described = first.get(f"/v1/sessions/{session_id}", headers=ADMIN).json()
    assert (described["last_seq"], described["batches"], described["epochs"]) == (7, 7, 21)


@pytest.mark.parametrize("how", ["deleted", "superseded", "revoked"])
def test_a_session_ended_through_one_worker_takes_no_batch_on_the_other(two_workers, how: str):
    first, second = two_workers
    key = first.post("/v1/vehicles", json={"vehicle_id": "car-9"}, headers=ADMIN).json()["key"]
    session_id, token = open_session(first, bearer(key), vehicle_id="car-9")
    url = f"/v1/sessions/{session_id}/batches"
    assert first.post(url, json=batch_body(1, 0, 3), headers=token).status_code == 200  # first caches it
    if how == "deleted":
        assert second.delete(f"/v1/sessions/{session_id}", headers=ADMIN).status_code == 204
    elif how == "superseded":
        newer, _ = open_session(second, bearer(key), vehicle_id="car-9")
    else:
        assert second.delete("/v1/vehicles/car-9", headers=ADMIN).status_code == 200
    refused = first.post(url, json=batch_body(2, 3, 3), headers=token)
    if how == "superseded":
        assert newer in assert_error(refused, 409, "superseded")["message"]
    else:
        assert_error(refused, 401, "unauthorized")
    # and the same again once the worker has forgotten the record: the answer of a fresh token check
    again = first.post(url, json=batch_body(2, 3, 3), headers=token)
    assert (again.status_code, again.json()["error"]["code"]) == (
        refused.status_code,
        refused.json()["error"]["code"],
    )
