"""The Redis Cluster store against a real local cluster (three primaries, three replicas, loopback).

Every store contract test runs here again. The contract tests name sessions freely ("s1", "old",
...), while on a cluster a session id carries its vehicle's shard; so they run through
:class:`IdMapping`, which gives each test id a real id from ``new_session_id`` and translates every id
in and out, and nothing else. The tests below it use real ids: the key layout (one slot per session),
the spread of sessions over the primaries, the session limit across shards, revocation racing a
create, and neighbour tracks read across slots.
"""

from __future__ import annotations

import asyncio
import dataclasses
import uuid
from collections import Counter
from collections.abc import Iterator
from typing import Any

import pytest
import redis
import test_store_contract as contract
from edgepos.pipelines.base import Rsu
from edgepos.store import SessionRecord, TooManySessions, open_store
from edgepos.store.base import Revocation, SessionSummary, Supersession, VehicleNotRegistered, VehicleRecord
from edgepos.store.redis_cluster import (
    SHARDS,
    RedisClusterStore,
    parse_cluster_url,
    shard_of_session,
    shard_of_vehicle,
    shard_tags,
)
from redis.crc import REDIS_CLUSTER_HASH_SLOTS, key_slot
from test_store_contract import Clock, record, track

_NOT_HERE = {"test_open_store_by_url", "test_sqlite_file_of_an_earlier_version_is_upgraded"}
globals().update(
    {
        name: test
        for name, test in vars(contract).items()
        if name.startswith("test_") and callable(test) and name not in _NOT_HERE
    }
)


class IdMapping:
    """The store under test with the contract tests' session ids mapped to ids of the vehicle's
    shard (shared by every handle of one test, as the ids are)."""

    def __init__(self, inner: RedisClusterStore, ids: dict[str, str]) -> None:
        self.inner, self.ids = inner, ids

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def _in(self, external: str) -> str:
        return self.ids.get(external, f"zz-unknown-{external}")  # not an id of ours: found nowhere

    def _out(self, internal: str | None) -> str | None:
        if internal is None:
            return None
        return next(external for external, mapped in self.ids.items() if mapped == internal)

    def _record_in(self, rec: SessionRecord) -> SessionRecord:
        if rec.session_id not in self.ids:
            self.ids[rec.session_id] = self.inner.new_session_id(rec.vehicle_id)
        return dataclasses.replace(rec, session_id=self.ids[rec.session_id])

    async def create(self, rec: SessionRecord, max_sessions: int, **kwargs: Any) -> str | None:
        return self._out(await self.inner.create(self._record_in(rec), max_sessions, **kwargs))

    async def get(self, session_id: str, *, with_response: bool = True) -> SessionRecord | None:
        got = await self.inner.get(self._in(session_id), with_response=with_response)
        return None if got is None else dataclasses.replace(got, session_id=session_id)

    async def compare_and_set(self, rec: SessionRecord, expected_version: int, fixes: Any = ()) -> bool:
        mapped = dataclasses.replace(rec, session_id=self._in(rec.session_id))
        return await self.inner.compare_and_set(mapped, expected_version, fixes)

    async def delete(self, session_id: str) -> bool:
        return await self.inner.delete(self._in(session_id))

    async def live_session(self, vehicle_id: str) -> str | None:
        return self._out(await self.inner.live_session(vehicle_id))

    async def supersession(self, session_id: str) -> Supersession | None:
        got = await self.inner.supersession(self._in(session_id))
        return (
            None
            if got is None
            else dataclasses.replace(got, session_id=session_id, superseded_by=self._out(got.superseded_by))
        )

    async def list_sessions(
        self, *, after: str | None = None, limit: int = 100, **filters: Any
    ) -> list[SessionSummary]:
        # the cluster store orders by its own ids; here the order is the test ids'
        every = await self.inner.list_sessions(limit=10**6, **filters)
        mapped = sorted(
            (dataclasses.replace(s, session_id=self._out(s.session_id)) for s in every),
            key=lambda s: s.session_id,
        )
        return [s for s in mapped if after is None or s.session_id > after][: max(0, limit)]

    async def put_track(self, trk: Any, session_id: str) -> bool:
        return await self.inner.put_track(trk, self._in(session_id))

    async def delete_vehicle(self, vehicle_id: str) -> Revocation | None:
        got = await self.inner.delete_vehicle(vehicle_id)
        return None if got is None else dataclasses.replace(got, ended_session=self._out(got.ended_session))

    async def make_durable(self, session_id: str) -> None:
        await self.inner.make_durable(self._in(session_id))


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def prefix() -> str:
    return f"t{uuid.uuid4().hex[:12]}:"


@pytest.fixture
def ids() -> dict[str, str]:
    return {}


@pytest.fixture
def cluster_store(redis_cluster: Any, prefix: str, clock: Clock) -> Iterator[RedisClusterStore]:
    instance = RedisClusterStore(redis_cluster.url(prefix), 60.0, clock)
    yield instance
    asyncio.run(instance.close())


@pytest.fixture
def store(cluster_store: RedisClusterStore, ids: dict[str, str]) -> IdMapping:
    return IdMapping(cluster_store, ids)


@pytest.fixture
def handles(
    store: IdMapping, redis_cluster: Any, prefix: str, clock: Clock, ids: dict[str, str]
) -> Iterator[list[Any]]:
    """More store objects on the same prefix, as other workers would hold."""
    others = [RedisClusterStore(redis_cluster.url(prefix), 60.0, clock) for _ in range(2)]
    yield [store, *(IdMapping(other, ids) for other in others)]
    for other in others:
        asyncio.run(other.close())


@pytest.fixture
def primaries(redis_cluster: Any) -> Iterator[list[redis.Redis]]:
    clients = [redis.Redis(host="127.0.0.1", port=node.port) for node in redis_cluster.primaries()]
    yield clients
    for client in clients:
        client.close()


def _keys(clients: list[redis.Redis], prefix: str) -> list[list[bytes]]:
    return [sorted(client.scan_iter(match=f"{prefix}*", count=1000)) for client in clients]


# the layout -----------------------------------------------------------------------------------
def test_shard_tags_lie_evenly_over_the_slots():
    tags = shard_tags()
    width = REDIS_CLUSTER_HASH_SLOTS // SHARDS
    assert len(tags) == len(set(tags)) == SHARDS
    assert [key_slot(tag.encode()) // width for tag in tags] == list(range(SHARDS))


def test_a_session_id_carries_its_vehicles_shard(cluster_store):
    for vehicle in ("car", "bus", "v-000017", "é"):
        session_id = cluster_store.new_session_id(vehicle)
        assert len(session_id) == 32 and int(session_id, 16) >= 0
        assert shard_of_session(session_id) == shard_of_vehicle(vehicle)


def test_every_key_of_a_session_is_in_one_slot(cluster_store, primaries, prefix):
    async def scenario() -> None:
        first = cluster_store.new_session_id("car")
        await cluster_store.create(record(first, vehicle_id="car"), max_sessions=10)
        await cluster_store.put_track(track("car"), first)
        second = cluster_store.new_session_id("car")
        assert await cluster_store.create(record(second, vehicle_id="car"), max_sessions=10) == first

    asyncio.run(scenario())
    keys = [key for node in _keys(primaries, prefix) for key in node]
    assert len(keys) == 4, keys  # the second session, the pointer, the supersession of the first, the index
    assert len({key_slot(key) for key in keys}) == 1


def test_a_create_with_a_foreign_session_id_is_refused(cluster_store):
    foreign = next(
        cluster_store.new_session_id(f"x{i}")
        for i in range(999)
        if shard_of_vehicle(f"x{i}") != shard_of_vehicle("car")
    )
    with pytest.raises(ValueError, match="shard"):
        asyncio.run(cluster_store.create(record(foreign, vehicle_id="car"), max_sessions=10))


def test_sessions_spread_over_the_three_primaries(cluster_store, primaries, prefix):
    vehicles = [f"veh-{i:05d}" for i in range(1500)]

    async def scenario() -> None:
        for start in range(0, len(vehicles), 100):
            await asyncio.gather(
                *(
                    cluster_store.create(
                        record(cluster_store.new_session_id(v), vehicle_id=v), max_sessions=10_000
                    )
                    for v in vehicles[start : start + 100]
                )
            )

    asyncio.run(scenario())
    per_node = [sum(1 for key in node if b":session:" in key) for node in _keys(primaries, prefix)]
    assert sum(per_node) == len(vehicles)
    for count in per_node:
        assert abs(count - len(vehicles) / 3) <= 0.1 * len(vehicles) / 3, per_node


def test_the_session_limit_counts_every_shard(cluster_store):
    vehicles = [f"lim-{i}" for i in range(12)]
    assert len({shard_of_vehicle(v) for v in vehicles}) > 6  # the sessions lie in several shards

    async def scenario() -> None:
        for v in vehicles[:10]:
            await cluster_store.create(record(cluster_store.new_session_id(v), vehicle_id=v), max_sessions=10)
        with pytest.raises(TooManySessions) as refused:
            await cluster_store.create(
                record(cluster_store.new_session_id(vehicles[10]), vehicle_id=vehicles[10]), max_sessions=10
            )
        assert refused.value.limit == 10
        assert await cluster_store.count() == 10
        # a vehicle's new session supersedes its old one and makes room for itself
        renewed = cluster_store.new_session_id(vehicles[0])
        assert (
            await cluster_store.create(record(renewed, vehicle_id=vehicles[0]), max_sessions=10) is not None
        )

    asyncio.run(scenario())


def test_list_sessions_pages_across_shards_in_id_order(cluster_store):
    async def scenario() -> list[str]:
        made = []
        for i in range(30):
            v = f"page-{i}"
            sid = cluster_store.new_session_id(v)
            await cluster_store.create(record(sid, vehicle_id=v), max_sessions=100)
            made.append(sid)
        seen: list[str] = []
        after = None
        while page := await cluster_store.list_sessions(after=after, limit=7):
            seen += [s.session_id for s in page]
            after = page[-1].session_id
        assert seen == sorted(made)
        return seen

    assert len(asyncio.run(scenario())) == 30


def test_tracks_of_vehicles_in_many_slots_are_read_together(cluster_store):
    vehicles = [f"nb-{i}" for i in range(40)]

    async def scenario() -> None:
        for v in vehicles:
            sid = cluster_store.new_session_id(v)
            await cluster_store.create(record(sid, vehicle_id=v), max_sessions=100)
            assert await cluster_store.put_track(track(v, 2), sid)
        got = await cluster_store.get_tracks([*vehicles, "nobody"])
        assert got == {v: track(v, 2) for v in vehicles}

    asyncio.run(scenario())


def test_a_vehicle_revoked_during_a_create_keeps_no_session(cluster_store, monkeypatch):
    key = "ab" * 32

    async def scenario() -> None:
        await cluster_store.add_vehicles([VehicleRecord("car", key, 1.0, 1.0)])
        checks = 0
        original = cluster_store._registered_with

        async def revoked_after_first_check(vehicle_id: str, key_hash: str) -> bool:
            nonlocal checks
            checks += 1
            registered = await original(vehicle_id, key_hash)
            if checks == 1:  # the revocation lands between the check and the create script
                assert await cluster_store.delete_vehicle("car") == Revocation("car", None)
            return registered

        monkeypatch.setattr(cluster_store, "_registered_with", revoked_after_first_check)
        sid = cluster_store.new_session_id("car")
        with pytest.raises(VehicleNotRegistered):
            await cluster_store.create(record(sid, vehicle_id="car"), max_sessions=10, vehicle_key_hash=key)
        assert await cluster_store.get(sid) is None
        assert await cluster_store.live_session("car") is None
        assert await cluster_store.count() == 0

    asyncio.run(scenario())


def test_registries_and_rate_budgets_are_single_keys(cluster_store, primaries, prefix):
    async def scenario() -> None:
        await cluster_store.upsert_rsus(
            [Rsu("r1", 0.0, 0.0, 1.0, 0.1, 100.0), Rsu("r2", 5.0, 0.0, 1.0, 0.1, 100.0)]
        )
        await cluster_store.add_vehicles([VehicleRecord("car", "cd" * 32, 1.0, 1.0)])
        await cluster_store.take_request("vehicle:car", contract.RateLimit(10.0, 5))

    asyncio.run(scenario())
    keys = [key.decode() for node in _keys(primaries, prefix) for key in node]
    assert sorted(keys) == sorted(
        [
            f"{prefix}rsus",
            f"{prefix}{{registry}}:vehicles",
            f"{prefix}{{registry}}:vehiclekeys",
            f"{prefix}rate:vehicle:car",
        ]
    )


def test_open_store_and_the_url(redis_cluster):
    store = open_store(redis_cluster.url("site-a:"), 60.0)
    assert isinstance(store, RedisClusterStore) and store.prefix == "site-a:"
    assert asyncio.run(store.ping())
    parsed = parse_cluster_url("redis-cluster://u:p%40ss@10.0.0.1:7000,[::1]:7001?socket_timeout=2&ssl=true")
    assert parsed["nodes"] == [("10.0.0.1", 7000), ("::1", 7001)]
    assert (
        parsed["client"]["password"] == "p@ss"
        and parsed["client"]["ssl"]
        and parsed["client"]["socket_timeout"] == 2.0
    )
    for bad in (
        "redis-cluster://host",
        "redis-cluster://h:1?db=2",
        "redis-cluster://h:1?prefix=a{b}",
        "redis://h:1",
    ):
        with pytest.raises(ValueError):
            parse_cluster_url(bad)
    counts = Counter(shard_of_vehicle(f"v{i}") for i in range(SHARDS * 40))
    assert len(counts) == SHARDS  # every shard is used
