"""The Redis store's per-worker caches (store.redis_cache) against a real redis-server: a batch applies on
the record its worker wrote last only while that is still the stored version, so two workers
interleaving writes lose no update, and a session deleted, superseded, revoked or expired between
batches is never written on a stale record; the RSU map a worker cached is refused by the write once
another worker changed the map; the record cache stays within its bound."""

from __future__ import annotations

import asyncio
import dataclasses
import multiprocessing
import time
import uuid
from collections.abc import Iterator
from typing import Any

import pytest
import redis
from edgepos.pipelines.base import Rsu
from edgepos.store import SessionRecord
from edgepos.store.base import VehicleRecord
from edgepos.store.fixlog import NewFix
from edgepos.store.redis import RedisStore
from edgepos.store.redis_cache import RSUS_USED
from test_store_contract import Clock, record

RedisServer = Any  # tests/store/conftest.py's RedisServer
WORKERS, INCREMENTS = 3, 30


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def prefix() -> str:
    return f"c{uuid.uuid4().hex[:12]}:"


@pytest.fixture
def workers(redis_server: RedisServer, prefix: str, clock: Clock) -> Iterator[tuple[RedisStore, RedisStore]]:
    """Two store objects on one Redis and prefix, as two worker processes hold them."""
    first, second = (RedisStore(redis_server.url(prefix), 60.0, clock) for _ in range(2))
    yield first, second
    asyncio.run(first.close())
    asyncio.run(second.close())


def run(coroutine: Any) -> Any:
    return asyncio.run(coroutine)


def next_batch(current: SessionRecord, clock: Clock, tag: bytes) -> SessionRecord:
    """What a batch writes: the state extended, one more batch, the next seq."""
    return dataclasses.replace(
        current,
        state=current.state + tag,
        batches=current.batches + 1,
        last_seq=current.last_seq + 1,
        updated_at=clock(),
    )


async def apply(store: RedisStore, session_id: str, clock: Clock, tag: bytes) -> int:
    """A batch as session_service applies it: on the record for a batch, redone on a fresh read when the
    compare-and-set refuses; returns how many attempts were refused."""
    refused = 0
    current = await store.get_for_batch(session_id)
    while True:
        assert current is not None
        if await store.compare_and_set(next_batch(current, clock, tag), current.version):
            return refused
        refused += 1
        current = await store.get(session_id)


def test_a_worker_skips_the_read_of_the_record_it_wrote(workers, raw_client, prefix: str, clock: Clock):
    first, _ = workers
    run(first.create(record("s1"), 10))
    assert run(apply(first, "s1", clock, b"a")) == 0
    raw_client.hset(f"{prefix}session:s1", "epochs", "77")  # a change that did not move the version
    cached = run(first.get_for_batch("s1"))
    assert cached is not None and cached.version == 1 and cached.epochs == 0  # not read from Redis
    assert cached.last_response is None  # the stored answer is never kept


def test_two_workers_interleaving_writes_lose_no_update(workers, clock: Clock):
    first, second = workers
    run(first.create(record("s1"), 10))
    assert run(apply(first, "s1", clock, b"a")) == 0  # first caches version 2
    assert run(apply(second, "s1", clock, b"b")) == 0  # second reads version 2, writes 3
    # first's cached version 2 is stale: its write is refused, and redone on the fresh record
    assert run(apply(first, "s1", clock, b"c")) == 1
    assert run(apply(first, "s1", clock, b"d")) == 0  # its own write is cached again
    final = run(first.get("s1"))
    assert final is not None
    assert (final.state, final.batches, final.version) == (b"\x00state\xffabcd", 4, 4)


@pytest.mark.parametrize("how", ["deleted", "superseded", "revoked", "expired"])
def test_a_session_gone_between_batches_is_never_written_on_the_cached_record(
    workers, raw_client, prefix: str, clock: Clock, how: str
):
    first, second = workers
    run(first.add_vehicles([VehicleRecord("car", "k" * 64, 1000.0, 1000.0)]))
    run(first.create(record("s1", vehicle_id="car"), 10))
    assert run(apply(first, "s1", clock, b"a")) == 0
    cached = run(first.get_for_batch("s1"))
    assert cached is not None
    if how == "deleted":
        assert run(second.delete("s1"))
    elif how == "superseded":
        assert run(second.create(record("s2", vehicle_id="car"), 10)) == "s1"
    elif how == "revoked":
        revocation = run(second.delete_vehicle("car"))
        assert revocation is not None and revocation.ended_session == "s1"
    else:
        clock.now += 61.0
    if how != "expired":
        assert not run(first.compare_and_set(next_batch(cached, clock, b"x"), cached.version))
    assert run(first.get_for_batch("s1")) is None
    assert raw_client.hget(f"{prefix}session:s1", "state") is None or how == "expired"
    if how == "expired":  # Redis has not dropped it yet (a fake clock); no worker answers from it
        assert raw_client.hget(f"{prefix}session:s1", "state") == b"\x00state\xffa"


def test_the_worker_that_deleted_a_session_forgets_it(workers, clock: Clock):
    first, _ = workers
    run(first.create(record("s1"), 10))
    assert len(first.records) == 1
    assert run(first.delete("s1"))
    assert len(first.records) == 0 and run(first.get_for_batch("s1")) is None


def test_the_record_cache_is_bounded_and_can_be_turned_off(redis_server: RedisServer, prefix: str, clock):
    small = RedisStore(redis_server.url(prefix, record_cache="2"), 60.0, clock)
    off = RedisStore(redis_server.url(prefix, record_cache="0"), 60.0, clock)
    for session_id in ("s1", "s2", "s3"):
        run(small.create(record(session_id), 10))
    assert len(small.records) == 2
    assert small.records.get("s1") is None and small.records.get("s3") is not None  # least recent went
    assert run(apply(off, "s2", clock, b"a")) == 0
    assert len(off.records) == 0
    run(small.close())
    run(off.close())


@pytest.mark.parametrize("value", ["-1", "many"])
def test_a_bad_record_cache_in_the_url_is_refused(redis_server: RedisServer, prefix: str, value: str):
    with pytest.raises(ValueError, match="record_cache"):
        RedisStore(redis_server.url(prefix, record_cache=value), 60.0)


def test_a_batch_on_a_cached_rsu_map_is_refused_once_the_map_changed(workers, clock: Clock):
    first, second = workers
    run(second.upsert_rsus([Rsu("r1", 0.0, 0.0, 1.0, 0.1, 100.0)]))
    run(first.create(record("s1"), 10))

    async def batch(store: RedisStore, tag: bytes) -> tuple[bool, float]:
        """One attempt as the batch path makes it: the token check's record, the RSUs, the write."""
        current = await store.get_for_batch("s1")
        assert current is not None
        rsus = await store.get_rsus(["r1"])
        return await store.compare_and_set(next_batch(current, clock, tag), current.version), rsus["r1"].x

    assert run(batch(first, b"a")) == (True, 0.0)  # first now holds the map
    run(second.upsert_rsus([Rsu("r1", 5.0, 0.0, 1.0, 0.1, 100.0)]))  # another worker moves the RSU
    assert run(batch(first, b"b")) == (False, 0.0)  # computed on the old map: refused, nothing written
    assert run(batch(first, b"c")) == (True, 5.0)  # the new map read again, written
    assert RSUS_USED.get() is None
    run(second.delete_rsu("r1"))
    assert run(batch(first, b"d")) == (False, 5.0)  # a deletion changes the token too
    final = run(first.get("s1"))
    assert final is not None and final.state == b"\x00state\xffac"


def test_the_fixes_of_a_batch_refused_for_a_changed_rsu_map_are_not_published(workers, clock: Clock):
    """The fix events that go with the write (``fixes_in_write``) are appended only by the writes that apply:
    not by the one computed on the old RSU map."""
    first, second = workers
    log = first.fix_log(100)
    run(second.upsert_rsus([Rsu("r1", 0.0, 0.0, 1.0, 0.1, 100.0)]))
    run(first.create(record("s1"), 10))

    async def batch(tag: bytes) -> bool:
        current = await first.get_for_batch("s1")
        assert current is not None
        await first.get_rsus(["r1"])
        events = [NewFix("s1", "v-s1", "rsu_imu", 1.0, tag)]
        return await first.compare_and_set(next_batch(current, clock, tag), current.version, events)

    assert first.fixes_in_write
    assert run(batch(b"a"))
    run(second.upsert_rsus([Rsu("r1", 5.0, 0.0, 1.0, 0.1, 100.0)]))
    assert not run(batch(b"b"))  # computed on the old map: refused, nothing written or published
    assert run(batch(b"c"))

    async def published() -> list[tuple[int, bytes]]:
        events = await log.read(0, 0.05, 10)
        await log.close()
        return [(event.id, event.data) for event in events]

    assert run(published()) == [(1, b"a"), (2, b"c")]


def _increment(url: str, session_id: str, count: int) -> int:
    """A worker process: ``count`` batches through the record cache; returns the refused attempts."""

    async def work() -> int:
        store = RedisStore(url, 3600.0)
        refused = 0
        for _ in range(count):
            refused += await apply(store, session_id, time.time, b"+")  # type: ignore[arg-type]
        await store.close()
        return refused

    return asyncio.run(work())


def test_concurrent_processes_on_cached_records_lose_no_update(redis_server: RedisServer, prefix: str):
    url = redis_server.url(prefix)
    store = RedisStore(url, 3600.0)
    now = time.time()
    run(store.create(SessionRecord("s", "car", "rsu_imu", {}, "h", b"", now, now), 10))
    with multiprocessing.get_context("spawn").Pool(WORKERS) as pool:
        pool.starmap(_increment, [(url, "s", INCREMENTS)] * WORKERS)
    final = run(store.get("s"))
    run(store.close())
    assert final is not None
    assert (final.batches, final.version) == (WORKERS * INCREMENTS, WORKERS * INCREMENTS)
    assert final.state == b"+" * (WORKERS * INCREMENTS)


@pytest.fixture
def raw_client(redis_server: RedisServer) -> Iterator[redis.Redis]:
    client = redis.Redis(host="127.0.0.1", port=redis_server.port, db=0)
    yield client
    client.close()


def test_an_rsu_map_read_by_a_batch_that_wrote_nothing_never_marks_the_next(workers):
    """A WebSocket's frames share one task: a frame refused after reading the RSUs must not leave the
    map's token for the next frame's write to be checked against."""
    first, _ = workers
    run(first.upsert_rsus([Rsu("r1", 0.0, 0.0, 1.0, 0.1, 100.0)]))
    run(first.create(record("s1"), 10))

    async def frames() -> tuple[str | None, str | None]:
        await first.get_for_batch("s1")
        await first.get_rsus(["r1"])  # then refused (422, 409...): no compare-and-set
        left = RSUS_USED.get()
        await first.get_for_batch("s1")  # the next frame's token check
        return left, RSUS_USED.get()

    left, next_frame = run(frames())
    assert left is not None and next_frame is None
