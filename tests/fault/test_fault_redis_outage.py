"""Redis goes away under a running service and comes back.

With the append-only file on (``appendfsync always``), ``kill -9`` of redis-server while a vehicle
has sessions: every session survives the restart at its last acknowledged seq. While Redis is down
the service neither hangs nor crashes: a batch gets 503 ``unavailable`` with Retry-After and a
message that names the store (and no host or port), /readyz is 503, /healthz stays 200. When Redis
is back the same service process is ready again by itself, and a vehicle whose client retried
through the outage saw no error at all.
"""

from __future__ import annotations

import asyncio
import threading
import time

import httpx
import pytest
from edgepos_client import AsyncEdgeposClient, EdgeposClient
from faulthelp import ADMIN, ADMIN_KEY, serve, start_state, stream_batches

pytestmark = pytest.mark.slow

BATCH_EPOCHS = 5
#: Redis stays down at least this long (s), and until the riding vehicle has been refused a batch.
OUTAGE_S = 2.0
#: Batches the riding vehicle sends once the service is ready again.
AFTER_RECOVERY = 3


class WatchingTransport(httpx.AsyncHTTPTransport):
    """Sets ``refused`` on a 503 answered while ``outage`` is set: the client is retrying through it."""

    def __init__(self, outage: threading.Event, refused: threading.Event) -> None:
        super().__init__()
        self.outage, self.refused = outage, refused

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        response = await super().handle_async_request(request)
        if response.status_code == 503 and self.outage.is_set():
            self.refused.set()
        return response


def test_redis_restart_with_aof_keeps_sessions_and_the_service_recovers_by_itself(tmp_path, redis_factory):
    redis = redis_factory("--appendonly", "yes", "--appendfsync", "always", "--save", "")
    redis.start()
    store_url = redis.url("outage:", socket_timeout="0.5", socket_connect_timeout="0.5")
    batches = stream_batches(0, BATCH_EPOCHS)
    with serve(tmp_path, 1, EDGEPOS_STORE=store_url, EDGEPOS_DEMO_RSUS="true") as server:
        with EdgeposClient(server.url, ADMIN_KEY, retries=0) as client:
            sessions = [client.create_session(f"aof-{i}", initial_state=start_state()) for i in range(3)]
            for number, session in enumerate(sessions):
                for k in range(number + 2):
                    client.send_batch(session, batches[k])
        # A vehicle that keeps streaming through the outage with a patient retry policy, kept in step
        # with the outage by events, not a timer (a busy machine outruns timers): Redis goes down after
        # its first batch is acknowledged and comes back only once the service has refused it a batch
        # (its client is then retrying through the outage); it stops AFTER_RECOVERY batches after the
        # service is ready again.
        riding: dict[str, object] = {}
        started = threading.Event()  # the rider's first batch was acknowledged
        outage = threading.Event()  # Redis is down
        refused = threading.Event()  # the rider got a 503 during the outage and is retrying
        recovered = threading.Event()  # the service is ready again

        def ride() -> None:
            async def go() -> None:
                transport = WatchingTransport(outage, refused)
                async with AsyncEdgeposClient(
                    server.url, ADMIN_KEY, timeout=5.0, retries=12, backoff=0.25, transport=transport
                ) as rider:
                    session = await rider.create_session("rider", initial_state=start_state())
                    sent = after_recovery = 0
                    while after_recovery < AFTER_RECOVERY and sent < len(batches):
                        back = recovered.is_set()
                        await rider.send_batch(session, batches[sent])
                        sent += 1
                        after_recovery += back
                        started.set()
                        await asyncio.sleep(0.1)
                    info = await rider.get_session(session)
                    riding.update(session=session, sent=sent, after_recovery=after_recovery, info=info)

            try:
                asyncio.run(go())
            except Exception as error:  # noqa: BLE001 - any failure of the rider is reported by the assertion below
                riding["error"] = error
            started.set()

        rider = threading.Thread(target=ride, daemon=True)
        rider.start()
        assert started.wait(30.0)

        redis.kill()
        outage.set()
        outage_started = time.monotonic()
        session = sessions[0]
        down = httpx.post(
            f"{server.url}/v1/sessions/{session.session_id}/batches",
            json={"seq": session.last_seq + 1, "measurements": [m.model_dump() for m in batches[2]]},
            headers={"Authorization": f"Bearer {session.token}"},
            timeout=10.0,
        )
        took = time.monotonic() - outage_started
        assert down.status_code == 503, down.text
        error = down.json()["error"]
        assert error["code"] == "unavailable" and "session store" in error["message"]
        assert str(redis.port) not in error["message"] and "127.0.0.1" not in error["message"]
        assert int(down.headers["Retry-After"]) >= 1
        assert took < 5.0, f"a batch took {took:.1f} s to fail with Redis down"
        assert httpx.get(f"{server.url}/readyz", timeout=10.0).status_code == 503
        assert httpx.get(f"{server.url}/healthz", timeout=10.0).status_code == 200
        opened = httpx.post(f"{server.url}/v1/sessions", json={"vehicle_id": "x"}, headers=ADMIN, timeout=10)
        assert opened.status_code == 503

        assert refused.wait(30.0), "the riding vehicle was never refused a batch while Redis was down"
        time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - outage_started)))  # down OUTAGE_S at least
        redis.start()  # same port, same directory: reads the append-only file back
        deadline = time.monotonic() + 10.0
        while httpx.get(f"{server.url}/readyz", timeout=5.0).status_code != 200:
            assert time.monotonic() < deadline, "the service did not become ready again by itself"
            time.sleep(0.1)
        assert server.process.poll() is None  # never restarted
        recovered.set()

        with EdgeposClient(server.url, ADMIN_KEY, retries=0) as client:
            for number, session in enumerate(sessions):
                info = client.get_session(session)
                assert (info.last_seq, info.batches) == (number + 2, number + 2)  # survived the kill
                client.send_batch(session, batches[number + 2])  # and go on at the next seq
                assert client.get_session(session).last_seq == number + 3
            assert len(client.list_rsus(sessions[0])) > 0  # the RSU registry survived too
        rider.join(60.0)
        assert not rider.is_alive()
    assert "error" not in riding, riding.get("error")
    info = riding["info"]
    assert info.last_seq == info.batches == riding["sent"]
    assert riding["after_recovery"] == AFTER_RECOVERY
