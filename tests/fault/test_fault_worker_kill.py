"""kill -9 one worker of ``edgepos serve --workers 2`` on Redis while vehicles stream batches.

Eight vehicles send batches back to back (closed loop, so both workers always have requests in
flight) through the Python client, which retries a batch with the same seq after a connection
error. Midway one worker gets SIGKILL. Afterwards: no vehicle saw an error (the requests lost with
the worker were retried and answered by a live worker), uvicorn replaced the dead worker, every
acknowledged batch is in Redis exactly once (last_seq, batches and epochs agree with what the
vehicles were told), and each session's stored filter state equals, byte for byte, the in-process
pipeline's after the same batches: a batch applied twice or skipped would change it.
"""

from __future__ import annotations

import asyncio
import os
import signal
import time

import httpx
import pytest
from edgepos.store.redis import RedisStore
from edgepos_client import AsyncEdgeposClient, EdgeposError
from faulthelp import ADMIN_KEY, reference_states, serve, start_state, stream_batches, wait_ready

pytestmark = pytest.mark.slow

VEHICLES = 8
STREAMS = 4
BATCH_EPOCHS = 10
KILL_AFTER_S = 2.5
STREAM_FOR_S = 7.0


class CountingTransport(httpx.AsyncHTTPTransport):
    """Counts transport errors (each one is a request the client then retries)."""

    errors = 0

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        try:
            return await super().handle_async_request(request)
        except httpx.TransportError:
            CountingTransport.errors += 1
            raise


async def _vehicle(url: str, index: int, stop_at: float) -> tuple[str, int, int, list[str]]:
    """Stream this vehicle's batches until ``stop_at``; returns session id, batches and epochs
    acknowledged, and any error the client raised (there should be none)."""
    batches = stream_batches(index % STREAMS, BATCH_EPOCHS)
    async with AsyncEdgeposClient(
        url, timeout=15.0, retries=6, backoff=0.1, transport=CountingTransport()
    ) as client:
        session = await client.create_session(f"kill-{index}", initial_state=start_state())
        acknowledged = epochs = 0
        errors: list[str] = []
        while time.monotonic() < stop_at and acknowledged < len(batches):
            try:
                fixes = await client.send_batch(session, batches[acknowledged])
            except EdgeposError as error:
                errors.append(f"{type(error).__name__}: {error}")
                break
            acknowledged += 1
            epochs += len(fixes)
        return session.session_id, acknowledged, epochs, errors


def test_killing_a_worker_loses_no_batch_and_fails_no_vehicle(tmp_path, redis_factory):
    redis = redis_factory("--save", "", "--appendonly", "no")
    redis.start()
    store_url = redis.url("kill:")
    with serve(tmp_path, 2, EDGEPOS_STORE=store_url, EDGEPOS_DEMO_RSUS="true") as server:
        before = server.worker_pids()
        assert len(before) == 2

        async def drive() -> list[tuple[str, int, int, list[str]]]:
            stop_at = time.monotonic() + STREAM_FOR_S
            vehicles = [asyncio.create_task(_vehicle(server.url, i, stop_at)) for i in range(VEHICLES)]
            await asyncio.sleep(KILL_AFTER_S)
            held = server.connections_by_worker()
            victim = max(held, key=held.__getitem__)  # the worker serving the most vehicles
            os.kill(victim, signal.SIGKILL)
            killed.append((victim, held))
            return await asyncio.gather(*vehicles)

        killed: list[tuple[int, dict[int, int]]] = []
        CountingTransport.errors = 0
        results = asyncio.run(drive())
        wait_ready(server, 30.0, workers=2)
        after = server.worker_pids()

        async def stored(session_ids: list[str]) -> list:
            store = RedisStore(store_url, 3600.0)
            try:
                return [await store.get(sid) for sid in session_ids]
            finally:
                await store.close()

        records = asyncio.run(stored([session_id for session_id, *_ in results]))

    assert [errors for *_, errors in results] == [[]] * VEHICLES
    (victim, held), = killed
    survivor = next(pid for pid in before if pid != victim)
    assert victim not in after and survivor in after and len(after) == 2, (before, after)  # replaced
    assert held[victim] >= 1, held
    print(f"killed worker {victim} holding {held[victim]} of {sum(held.values())} connections; "
          f"{CountingTransport.errors} transport error(s) retried; acknowledged {[r[1] for r in results]}")
    assert CountingTransport.errors >= 1, "the kill hit no request in flight: the test proved nothing"
    references: dict[int, list[bytes]] = {}
    for index, ((_sid, acknowledged, epochs, _errors), record) in enumerate(zip(results, records, strict=True)):
        assert acknowledged >= 5, f"vehicle {index} made too little progress to test anything"
        assert record is not None
        assert (record.last_seq, record.batches, record.epochs) == (acknowledged, acknowledged, epochs)
        stream = index % STREAMS
        if len(references.get(stream, [])) <= acknowledged:
            most = max(a for i, (_s, a, _e, _r) in enumerate(results) if i % STREAMS == stream)
            references[stream] = reference_states(stream, BATCH_EPOCHS, most)
        assert record.state == references[stream][acknowledged], f"vehicle {index}: state differs"
    assert ADMIN_KEY not in server.log()
