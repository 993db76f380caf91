"""kill -9 one worker of ``edgepos serve --workers 2`` on Redis while vehicles stream batches.

The batches carry late measurements (30 % of the RSU measurements 0.05-0.5 s late, so the lag window
replays from its checkpoints on many batches): a late batch applied twice or lost would show below.

Eight vehicles send batches back to back (closed loop, so both workers always have requests in flight)
through the Python client, which retries a batch with the same seq after a connection error. Once every
vehicle is streaming (a few batches acknowledged each, not a fixed delay, which a busy machine can
outrun) one worker gets SIGKILL, and the vehicles stream on for a few seconds and a few more batches
each (a count as well as a time: a busy machine serves fewer batches per second). Afterwards: no vehicle
saw an error (the requests lost with the worker were retried and answered by a live worker), uvicorn
replaced the dead worker, every acknowledged batch is in Redis exactly once (last_seq, batches and
epochs agree with what the vehicles were told), and each session's stored filter state equals, byte for
byte, the in-process pipeline's after the same batches: a batch applied twice or skipped would change
it.
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
from faulthelp import (
    ADMIN_KEY,
    SERVER_READY_S,
    reference_states,
    serve,
    start_state,
    stream_batches,
    wait_ready,
)

pytestmark = pytest.mark.slow

VEHICLES = 8
STREAMS = 4
BATCH_EPOCHS = 10
#: Batches every vehicle has acknowledged before the kill.
WARM_UP_BATCHES = 3
#: How long the vehicles stream on after the kill, at least (s).
STREAM_AFTER_KILL_S = 4.5
#: Batches every vehicle has acknowledged after the kill before it stops, at least.
AFTER_KILL_BATCHES = 2
#: Bound on the warm-up: a server that cannot serve three batches per vehicle by then is broken (s).
WARM_UP_TIMEOUT_S = 60.0


class CountingTransport(httpx.AsyncHTTPTransport):
    """Counts transport errors (each one is a request the client then retries), and its own requests."""

    errors = 0

    def __init__(self) -> None:
        super().__init__()
        self.started = 0

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        self.started += 1
        try:
            return await super().handle_async_request(request)
        except httpx.TransportError:
            CountingTransport.errors += 1
            raise


class Progress:
    """What the vehicles have acknowledged so far, and what each had when the worker was killed."""

    def __init__(self, vehicles: int) -> None:
        self.acknowledged = [0] * vehicles
        self.transports: list[CountingTransport] = []
        self.at_kill: list[int] | None = None
        self.stream_until = float("inf")

    def kill(self) -> list[int]:
        """Mark the kill: returns what each vehicle had acknowledged by then."""
        self.at_kill = list(self.acknowledged)
        self.stream_until = time.monotonic() + STREAM_AFTER_KILL_S
        return self.at_kill

    def done(self, index: int, acknowledged: int) -> bool:
        """Vehicle ``index`` may stop: STREAM_AFTER_KILL_S have passed since the kill and it has had
        AFTER_KILL_BATCHES batches acknowledged since."""
        return (
            self.at_kill is not None
            and acknowledged >= self.at_kill[index] + AFTER_KILL_BATCHES
            and time.monotonic() >= self.stream_until
        )


async def _vehicle(
    url: str, index: int, batches: tuple, progress: Progress
) -> tuple[str, int, int, list[str]]:
    """Stream this vehicle's batches until ``progress`` says it is done; returns session id, batches and
    epochs acknowledged, and any error the client raised (there should be none)."""
    transport = CountingTransport()
    progress.transports.append(transport)
    async with AsyncEdgeposClient(
        url, ADMIN_KEY, timeout=15.0, retries=6, backoff=0.1, transport=transport
    ) as client:
        session = await client.create_session(f"kill-{index}", initial_state=start_state())
        acknowledged = epochs = 0
        errors: list[str] = []
        while not progress.done(index, acknowledged) and acknowledged < len(batches):
            try:
                fixes = await client.send_batch(session, batches[acknowledged])
            except EdgeposError as error:
                errors.append(f"{type(error).__name__}: {error}")
                break
            acknowledged += 1
            progress.acknowledged[index] = acknowledged
            epochs += sum(not fix.revised for fix in fixes)  # a revised fix is an epoch answered before
        return session.session_id, acknowledged, epochs, errors


def test_killing_a_worker_loses_no_batch_and_fails_no_vehicle(tmp_path, redis_factory):
    redis = redis_factory("--save", "", "--appendonly", "no")
    redis.start()
    store_url = redis.url("kill:")
    with serve(tmp_path, 2, EDGEPOS_STORE=store_url, EDGEPOS_DEMO_RSUS="true") as server:
        before = server.worker_pids()
        assert len(before) == 2

        streams = [stream_batches(stream, BATCH_EPOCHS, late=True) for stream in range(STREAMS)]

        async def drive() -> list[tuple[str, int, int, list[str]]]:
            progress = Progress(VEHICLES)
            vehicles = [
                asyncio.create_task(_vehicle(server.url, i, streams[i % STREAMS], progress))
                for i in range(VEHICLES)
            ]
            warm_up_ends = time.monotonic() + WARM_UP_TIMEOUT_S
            while min(progress.acknowledged) < WARM_UP_BATCHES:
                assert time.monotonic() < warm_up_ends, f"vehicles did not get going: {progress.acknowledged}"
                assert not any(v.done() for v in vehicles), [v.result() for v in vehicles if v.done()]
                await asyncio.sleep(0.05)
            held = server.connections_by_worker()
            victim = max(held, key=held.__getitem__)  # the worker serving the most vehicles
            # That scan held up this event loop while the workers answered whatever was in flight (on a
            # busy machine, everything): kill once every vehicle has sent its next batch since, so that
            # the victim dies with requests in flight. No await between this wait and the kill.
            started = [transport.started for transport in progress.transports]
            resent_by = time.monotonic() + WARM_UP_TIMEOUT_S
            while any(t.started == n for t, n in zip(progress.transports, started, strict=True)):
                assert time.monotonic() < resent_by, "the vehicles stopped sending"
                await asyncio.sleep(0)
            at_kill = progress.kill()
            os.kill(victim, signal.SIGKILL)
            killed.append((victim, held, at_kill))
            return await asyncio.gather(*vehicles)

        killed: list[tuple[int, dict[int, int], list[int]]] = []
        CountingTransport.errors = 0
        results = asyncio.run(drive())
        wait_ready(server, SERVER_READY_S, workers=2)  # uvicorn's replacement worker
        after = server.worker_pids()

        async def stored(session_ids: list[str]) -> list:
            store = RedisStore(store_url, 3600.0)
            try:
                return [await store.get(sid) for sid in session_ids]
            finally:
                await store.close()

        records = asyncio.run(stored([session_id for session_id, *_ in results]))

    assert [errors for *_, errors in results] == [[]] * VEHICLES
    ((victim, held, at_kill),) = killed
    survivor = next(pid for pid in before if pid != victim)
    assert victim not in after and survivor in after and len(after) == 2, (before, after)  # replaced
    assert held[victim] >= 1, held
    print(
        f"killed worker {victim} holding {held[victim]} of {sum(held.values())} connections; "
        f"{CountingTransport.errors} transport error(s) retried; acknowledged {[r[1] for r in results]}"
    )
    assert CountingTransport.errors >= 1, "the kill hit no request in flight: the test proved nothing"
    references: dict[int, list[bytes]] = {}
    for index, ((_sid, acknowledged, epochs, _errors), record) in enumerate(
        zip(results, records, strict=True)
    ):
        at_least = min(len(streams[index % STREAMS]), at_kill[index] + AFTER_KILL_BATCHES)
        assert acknowledged >= at_least, f"vehicle {index} stopped at {acknowledged} of {at_least} batches"
        assert record is not None
        assert (record.last_seq, record.batches, record.epochs) == (acknowledged, acknowledged, epochs)
        stream = index % STREAMS
        if len(references.get(stream, [])) <= acknowledged:
            most = max(a for i, (_s, a, _e, _r) in enumerate(results) if i % STREAMS == stream)
            references[stream] = reference_states(stream, BATCH_EPOCHS, most, late=True)
        assert record.state == references[stream][acknowledged], f"vehicle {index}: state differs"
    assert ADMIN_KEY not in server.log()
