"""MEC 013 location subscriptions on a real server with two workers sharing Redis: a subscription made
through either worker is seen by both, its notifications reach a receiver on 127.0.0.1 once each (one
notifier holds the store lease), and its deletion holds everywhere."""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import pytest
from apihelp import ADMIN, ADMIN_KEY, batch_body, rsu_payload
from callbackhelp import receiver
from edgepos.loadgen.localredis import RedisServer
from edgepos.loadgen.localserver import clean_environment, running, serve_command
from test_api_location_events import GATE, zone_subscription

pytestmark = pytest.mark.slow


def test_two_workers_on_redis_notify_each_crossing_once(tmp_path: Path, redis_server: RedisServer):
    environment = clean_environment(
        EDGEPOS_STORE=redis_server.url("location:"),
        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
        EDGEPOS_ORIGIN_LAT="48.137",
        EDGEPOS_ORIGIN_LON="11.575",
        EDGEPOS_LOCATION_POLL_S="0.1",
        EDGEPOS_RATE_LIMIT_PER_S="0",
        EDGEPOS_LOG_LEVEL="warning",
    )
    with (
        running(serve_command(2), environment, tmp_path / "server.log", ready_timeout_s=300.0) as base,
        receiver() as sink,
    ):
        assert httpx.put(f"{base}/v1/rsus", json=rsu_payload(), headers=ADMIN, timeout=30).status_code == 200
        assert httpx.put(f"{base}/v1/zones/gate", json=GATE, headers=ADMIN, timeout=30).status_code == 200
        created = httpx.post(
            f"{base}/v1/sessions", json={"vehicle_id": "car-1"}, headers=ADMIN, timeout=30
        ).json()
        session, token = created["session_id"], {"Authorization": f"Bearer {created['token']}"}

        def drive(seq: int, first: int, count: int) -> None:
            # a new connection per request: the kernel hands connections to either worker
            answer = httpx.post(
                f"{base}/v1/sessions/{session}/batches",
                json=batch_body(seq, first, count),
                headers=token,
                timeout=60,
            )
            assert answer.status_code == 200, answer.text

        drive(1, 0, 20)
        subscription = httpx.post(
            f"{base}/location/v3/subscriptions/zones",
            json=zone_subscription(sink.url),
            headers=ADMIN,
            timeout=30,
        )
        assert subscription.status_code == 201, subscription.text
        location = subscription.headers["location"]
        for _ in range(6):  # every worker sees it, whichever answers
            assert httpx.get(location, headers=ADMIN, timeout=30).status_code == 200
        drive(2, 20, 130)
        sink.wait_for(lambda bodies: len(bodies) >= 1, timeout_s=30)
        drive(3, 150, 150)
        sink.wait_for(lambda bodies: len(bodies) >= 2, timeout_s=30)
        time.sleep(1.0)  # ten polls of each worker
        events = [body["userLocationEvent"] for body in sink.received()]
        assert events == ["ENTERING_AREA_EVENT", "LEAVING_AREA_EVENT"]
        assert httpx.delete(location, headers=ADMIN, timeout=30).status_code == 204
        for _ in range(6):
            assert httpx.get(location, headers=ADMIN, timeout=30).status_code == 404
