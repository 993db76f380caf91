"""The Redis store against a real redis-server on loopback: the same contract as the other stores,
no lost update between processes, TTL expiry in Redis itself, sessions surviving a Redis restart
with the append-only file on, and an unreachable Redis failing fast with StoreUnavailable."""

from __future__ import annotations

import asyncio
import dataclasses
import multiprocessing
import socket
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import redis
import test_store_contract as contract
from edgepos.pipelines.base import Rsu
from edgepos.store import SessionRecord, TooManySessions, open_store
from edgepos.store.base import StoreUnavailable, VehicleRecord
from edgepos.store.redis import RedisStore
from test_store_contract import Clock, record, track

# Every store contract test runs here again, on the Redis store below (the URL test is about
# open_store itself, the upgrade test about SQLite files). New contract tests are picked up automatically.
_NOT_REDIS = {"test_open_store_by_url", "test_sqlite_file_of_an_earlier_version_is_upgraded"}
globals().update(
    {
        name: test
        for name, test in vars(contract).items()
        if name.startswith("test_") and callable(test) and name not in _NOT_REDIS
    }
)

INCREMENTS = 40
WORKERS = 3
RedisServer = Any  # tests/store/conftest.py's RedisServer (conftest modules are not importable by name)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def prefix() -> str:
    return f"t{uuid.uuid4().hex[:12]}:"


@pytest.fixture
def store(redis_server: RedisServer, prefix: str, clock: Clock) -> Iterator[RedisStore]:
    instance = RedisStore(redis_server.url(prefix), 60.0, clock)
    yield instance
    asyncio.run(instance.close())


@pytest.fixture
def handles(
    store: RedisStore, redis_server: RedisServer, prefix: str, clock: Clock
) -> Iterator[list[RedisStore]]:
    """More store objects on the same prefix, as other workers would hold."""
    others = [RedisStore(redis_server.url(prefix), 60.0, clock) for _ in range(2)]
    yield [store, *others]
    for other in others:
        asyncio.run(other.close())


@pytest.fixture
def raw(redis_server: RedisServer) -> Iterator[redis.Redis]:
    """A plain synchronous client to look at what the store wrote."""
    client = redis.Redis(host="127.0.0.1", port=redis_server.port, db=0)
    yield client
    client.close()


def test_open_store_selects_redis(redis_server: RedisServer):
    store = open_store(redis_server.url("site-a:", socket_timeout="2.5"), 10.0)
    assert isinstance(store, RedisStore)
    assert store.prefix == "site-a:" and "socket_timeout=2.5" in store.url and "prefix" not in store.url
    assert RedisStore(redis_server.url(), 10.0).prefix == "edgepos:"
    with pytest.raises(ValueError):
        RedisStore(redis_server.url() + "?prefix=", 10.0)
    with pytest.raises(ValueError):
        RedisStore("http://127.0.0.1:1/0", 10.0)


def test_key_layout_binary_state_and_replay_fields(store: RedisStore, prefix: str, raw: redis.Redis):
    state = bytes(range(256))

    async def scenario() -> None:
        await store.create(record(state=state), max_sessions=10)
        current = await store.get("s1")
        replayed = dataclasses.replace(
            current, last_seq=1, last_request_hash="h1", last_response=b'{"seq":1}\x00', last_fix="f"
        )
        assert await store.compare_and_set(replayed, 0)
        assert await store.get("s1") == dataclasses.replace(replayed, version=1)
        # the batch route's token check reads without the stored answer (HMGET of the other fields)
        assert await store.get("s1", with_response=False) == dataclasses.replace(
            replayed, version=1, last_response=None
        )
        # a later write without replay data clears the old fields rather than keeping them
        cleared = dataclasses.replace(replayed, last_request_hash=None, last_response=None, last_fix=None)
        assert await store.compare_and_set(cleared, 1)
        assert await store.get("s1") == dataclasses.replace(cleared, version=2)
        await store.upsert_rsus([Rsu("r1", 1.0, 2.0)])

    asyncio.run(scenario())
    key = f"{prefix}session:s1"
    assert raw.hget(key, "state") == state  # raw bytes, not base64 or JSON
    assert raw.hget(key, "version") == b"2"
    assert not raw.hexists(key, "last_response")
    assert raw.type(f"{prefix}sessions") == b"zset" and raw.zscore(f"{prefix}sessions", "s1") == 1000.0
    assert raw.type(f"{prefix}rsus") == b"hash"
    assert raw.get(f"{prefix}live:v-s1") == b"s1"
    assert sorted(raw.scan_iter(match=f"{prefix}*")) == sorted(
        [
            key.encode(),
            f"{prefix}sessions".encode(),
            f"{prefix}rsus".encode(),
            f"{prefix}rsus:token".encode(),
            f"{prefix}live:v-s1".encode(),
        ]
    )


def test_a_write_goes_through_a_staged_hash_that_never_outlives_it(
    redis_server: RedisServer, prefix: str, clock: Clock, raw: redis.Redis
):
    """The new record is staged beside the session's key and renamed into place only if the version is
    still the one read: a losing writer leaves the session and no staged key behind, and a server that lost
    the script (SCRIPT FLUSH, a restart) gets it again without failing the write."""

    store = RedisStore(redis_server.url(prefix), 600.0, clock)

    async def scenario() -> None:
        await store.create(record(), max_sessions=10)
        current = await store.get("s1")
        assert await store.compare_and_set(dataclasses.replace(current, last_seq=1, batches=1), 0)
        stale = dataclasses.replace(current, last_seq=7, last_response=b"lost")
        assert not await store.compare_and_set(stale, 0)  # version 0 is gone
        assert (await store.get("s1")).last_seq == 1
        raw.script_flush()
        assert await store.compare_and_set(dataclasses.replace(current, last_seq=2, batches=2), 1)
        assert (await store.get("s1")).version == 2
        await store.close()

    asyncio.run(scenario())
    assert list(raw.scan_iter(match=f"{prefix}session:*")) == [f"{prefix}session:s1".encode()]
    assert raw.hget(f"{prefix}session:s1", "last_seq") == b"2"
    assert raw.pttl(f"{prefix}session:s1") > 60_000  # the session's TTL (600 s), not the staged hash's (60 s)


def test_key_layout_of_vehicles_live_pointers_and_supersessions(
    store: RedisStore, prefix: str, raw: redis.Redis
):
    """The registry is two hashes; a live pointer and a supersession record carry the session TTL,
    and each write to the session sets the pointer's TTL again."""
    key_1, key_2 = "k1" * 32, "k2" * 32

    async def scenario() -> None:
        await store.add_vehicles([VehicleRecord("car", key_1, 1000.1, 1000.2)])
        await store.create(record("s1", vehicle_id="car"), max_sessions=10, vehicle_key_hash=key_1)
        assert await store.put_track(track("car"), "s1")

    asyncio.run(scenario())
    assert raw.type(f"{prefix}vehicles") == b"hash" and raw.type(f"{prefix}vehiclekeys") == b"hash"
    assert raw.hget(f"{prefix}vehiclekeys", key_1) == b"car"
    assert raw.get(f"{prefix}live:car") == b"s1"
    assert 0 < raw.pttl(f"{prefix}live:car") <= 60_000
    raw.pexpire(f"{prefix}live:car", 5_000)

    async def write_and_supersede() -> None:
        current = await store.get("s1")
        assert await store.compare_and_set(dataclasses.replace(current, state=b"next"), 0)
        assert raw.pttl(f"{prefix}live:car") > 5_000  # refreshed with the session's TTL
        await store.rotate_vehicle_key("car", key_2, 1100.5)
        renewed = await store.create(record("s2", vehicle_id="car"), max_sessions=10, vehicle_key_hash=key_2)
        assert renewed == "s1"

    asyncio.run(write_and_supersede())
    assert raw.hget(f"{prefix}vehiclekeys", key_1) is None
    assert raw.hget(f"{prefix}vehiclekeys", key_2) == b"car"
    assert raw.hgetall(f"{prefix}superseded:s1") == {
        b"superseded_by": b"s2",
        b"token_hash": b"ab" * 32,
        b"at": b"1000.0",
    }
    assert 0 < raw.pttl(f"{prefix}superseded:s1") <= 60_000
    assert raw.exists(f"{prefix}session:s1", f"{prefix}track:car") == 0
    assert raw.get(f"{prefix}live:car") == b"s2"

    asyncio.run(store.delete_vehicle("car"))  # the registry, pointer, session and index empty out
    assert list(raw.scan_iter(match=f"{prefix}*")) == [f"{prefix}superseded:s1".encode()]


def test_a_pointer_to_a_session_redis_dropped_is_absent(store: RedisStore, prefix: str, raw: redis.Redis):
    """Redis may expire a session's hash before the pointer naming it (or before the index entry):
    the vehicle then has no live session, publishes nothing, and its next session supersedes nothing
    and is not refused by the limit for it."""

    async def scenario() -> None:
        await store.create(record("s1", vehicle_id="car"), max_sessions=1)
        raw.delete(f"{prefix}session:s1")
        assert await store.live_session("car") is None
        assert not await store.put_track(track("car"), "s1")
        assert await store.list_sessions() == [] and await store.list_sessions(vehicle_id="car") == []
        assert await store.create(record("s2", vehicle_id="car"), max_sessions=1) is None
        assert await store.supersession("s1") is None
        assert await store.live_session("car") == "s2"
        assert await store.count() == 1

    asyncio.run(scenario())


def test_prefixes_keep_sites_apart(redis_server: RedisServer, clock: Clock):
    async def scenario() -> None:
        first = RedisStore(redis_server.url("site-a:"), 60.0, clock)
        second = RedisStore(redis_server.url("site-b:"), 60.0, clock)
        await first.create(record("shared-id", vehicle_id="car"), max_sessions=1)
        await second.create(record("shared-id", vehicle_id="other"), max_sessions=1)
        assert (await first.get("shared-id")).vehicle_id == "car"
        assert await first.live_session("car") == "shared-id" and await second.live_session("car") is None
        assert await first.count() == 1 and await second.count() == 1
        await first.upsert_rsus([Rsu("r", 0.0, 0.0)])
        assert await second.list_rsus() == []
        for instance in (first, second):
            await instance.delete("shared-id")
            await instance.delete_rsu("r")
            await instance.close()

    asyncio.run(scenario())


def test_session_limit_holds_under_concurrent_creates(redis_server: RedisServer, prefix: str):
    """Two store objects (as two workers would) race 20 creates for 5 places: exactly 5 win."""

    async def scenario() -> tuple[int, int]:
        stores = [RedisStore(redis_server.url(prefix), 60.0) for _ in range(2)]
        now = time.time()

        async def attempt(i: int) -> bool:
            try:
                await stores[i % 2].create(record(f"s{i}", now=now), max_sessions=5)
            except TooManySessions:
                return False
            return True

        won = await asyncio.gather(*(attempt(i) for i in range(20)))
        count = await stores[0].count()
        for instance in stores:
            await instance.close()
        return sum(won), count

    assert asyncio.run(scenario()) == (5, 5)


def test_a_burst_wider_than_the_pool_waits_for_connections(
    redis_server: RedisServer, prefix: str, raw: redis.Redis
):
    """300 concurrent creates through a pool of 4 connections all succeed (they queue for a
    connection instead of opening 300 sockets), and the store never holds more than 4."""

    async def scenario() -> tuple[int, int]:
        name = f"burst{uuid.uuid4().hex[:8]}"
        instance = RedisStore(redis_server.url(prefix, max_connections="4", client_name=name), 60.0)
        now = time.time()
        await asyncio.gather(
            *(instance.create(record(f"b{i}", now=now), max_sessions=1000) for i in range(300))
        )
        opened = sum(1 for client in raw.client_list() if client.get("name") == name)
        count = await instance.count()
        await instance.close()
        return count, opened

    count, opened = asyncio.run(scenario())
    assert count == 300
    assert 1 <= opened <= 4


def _increment(url: str, session_id: str, count: int) -> int:
    """A worker process: add 1 to ``batches`` ``count`` times by load + compare-and-set + retry."""

    async def work() -> int:
        store = RedisStore(url, 3600.0)
        conflicts = 0
        for _ in range(count):
            while True:
                current = await store.get(session_id)
                assert current is not None
                updated = dataclasses.replace(
                    current, batches=current.batches + 1, state=current.state + b"+", updated_at=time.time()
                )
                if await store.compare_and_set(updated, current.version):
                    break
                conflicts += 1
        await store.close()
        return conflicts

    return asyncio.run(work())


def test_concurrent_processes_lose_no_update(redis_server: RedisServer, prefix: str):
    url = redis_server.url(prefix)
    store = RedisStore(url, 3600.0)
    now = time.time()
    asyncio.run(store.create(SessionRecord("s", "car", "rsu_imu", {}, "h", b"", now, now), 10))
    context = multiprocessing.get_context("spawn")
    with context.Pool(WORKERS) as pool:
        pool.starmap(_increment, [(url, "s", INCREMENTS)] * WORKERS)
    final = asyncio.run(store.get("s"))
    asyncio.run(store.close())
    assert final is not None
    assert final.batches == WORKERS * INCREMENTS
    assert final.version == WORKERS * INCREMENTS
    assert final.state == b"+" * (WORKERS * INCREMENTS)


def test_redis_ttl_is_refreshed_by_each_write_and_expires_idle_sessions(
    redis_server: RedisServer, prefix: str, raw: redis.Redis
):
    key = f"{prefix}session:s1"
    ttl_s = 2.0  # margins of 0.8 s around each expiry, so a stalled machine cannot flip a check

    async def scenario() -> None:
        store = RedisStore(redis_server.url(prefix), ttl_s)
        await store.create(record(now=time.time()), max_sessions=5)
        assert 0 < raw.pttl(key) <= 2000
        await asyncio.sleep(1.0)
        current = await store.get("s1")
        assert await store.compare_and_set(dataclasses.replace(current, updated_at=time.time()), 0)
        assert raw.pttl(key) > 1500  # refreshed by the write
        await asyncio.sleep(1.2)  # 2.2 s after creation, 1.2 s after the write
        assert await store.get("s1") is not None
        await asyncio.sleep(1.0)  # now idle 2.2 s > ttl: Redis itself dropped the key
        assert raw.exists(key) == 0
        assert await store.get("s1") is None
        assert await store.count() == 0
        assert raw.zcard(f"{prefix}sessions") == 0
        await store.close()

    asyncio.run(scenario())


def test_sessions_survive_a_redis_kill_and_restart_with_aof(redis_factory: Callable[..., RedisServer]):
    """SIGKILL redis-server (no shutdown save) with appendonly on: every acknowledged write is back
    after the restart; while it is down calls fail fast; the same store objects recover by themselves,
    including one whose pooled connection went stale during the outage without being used."""
    server = redis_factory("--appendonly", "yes", "--appendfsync", "always", "--save", "")
    server.start()
    url = server.url("aof:", socket_timeout="0.5", socket_connect_timeout="0.5")

    async def scenario() -> None:
        store, idle = RedisStore(url, 3600.0), RedisStore(url, 3600.0)
        await store.create(record("kept", now=time.time()), max_sessions=10)
        current = await store.get("kept")
        updated = dataclasses.replace(current, state=b"after batch 1", last_seq=1, last_response=b"{}")
        assert await store.compare_and_set(updated, 0)
        await store.upsert_rsus([Rsu("r1", 3.0, 4.0)])
        assert await idle.get_rsu("r1") is not None  # leaves a pooled connection behind

        server.kill()
        started = time.monotonic()
        with pytest.raises(StoreUnavailable):
            await store.get("kept")
        with pytest.raises(StoreUnavailable):
            await store.ping()
        assert time.monotonic() - started < 3.0

        server.start()
        assert await store.ping()
        assert await store.get("kept") == dataclasses.replace(updated, version=1)
        assert await idle.get_rsu("r1") == Rsu("r1", 3.0, 4.0)  # stale connection replaced on retry
        assert await idle.count() == 1
        await store.close()
        await idle.close()

    asyncio.run(scenario())


@pytest.mark.parametrize("kind", ["refused", "silent"])
def test_unreachable_redis_is_a_typed_error_within_a_bounded_time(kind: str):
    """Nobody listening (connection refused) and a peer that accepts but never answers both end
    in StoreUnavailable quickly, for reads, writes and the readiness ping."""
    silent = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if kind == "silent":
        silent.bind(("127.0.0.1", 0))
        silent.listen(64)  # the kernel completes handshakes; nothing ever reads or replies
        port = silent.getsockname()[1]
    else:
        port = free_port()
    url = f"redis://127.0.0.1:{port}/0?socket_timeout=0.3&socket_connect_timeout=0.3"
    store = RedisStore(url, 60.0)
    operations = {
        "get": lambda: store.get("s1"),
        "create": lambda: store.create(record(), max_sessions=5),
        "compare_and_set": lambda: store.compare_and_set(record(), 0),
        "count": store.count,
        "get_rsus": lambda: store.get_rsus(["a"]),
        "ping": store.ping,
    }

    async def scenario() -> dict[str, float]:
        took: dict[str, float] = {}
        for name, operation in operations.items():
            started = time.monotonic()
            with pytest.raises(StoreUnavailable):
                await asyncio.wait_for(operation(), 10.0)  # a hang would show as TimeoutError
            took[name] = time.monotonic() - started
        await store.close()
        return took

    try:
        took = asyncio.run(scenario())
    finally:
        silent.close()
    assert max(took.values()) < 2.0, took
