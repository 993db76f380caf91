"""EDGEPOS_REDIS_WAIT_REPLICAS: a batch is acknowledged only once a replica holds it (Redis WAIT), against
a real primary and replica on loopback. With the replica down the write stays on the primary and is
refused as NotReplicated (a 503 at the service); once the replica is back the same write is durable."""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Callable
from typing import Any

import pytest
from edgepos.store import open_store
from edgepos.store.base import NotReplicated
from edgepos.store.redis import RedisStore
from test_store_contract import record

RedisServer = Any  # tests/store/conftest.py's RedisServer


def replicated_pair(redis_factory: Callable[..., RedisServer]) -> tuple[RedisServer, RedisServer]:
    primary = redis_factory("--save", "", "--appendonly", "no")
    primary.start()
    replica = redis_factory("--save", "", "--appendonly", "no", "--replicaof", "127.0.0.1", str(primary.port))
    replica.start()
    wait_for_link(primary, replica)
    return primary, replica


def wait_for_link(primary: RedisServer, replica: RedisServer) -> None:
    deadline = time.monotonic() + 30.0
    while b"master_link_status:up" not in replica.command("INFO", "replication"):
        assert time.monotonic() < deadline, "the replica did not connect to its primary"
        time.sleep(0.05)
    while b"connected_slaves:1" not in primary.command("INFO", "replication"):
        assert time.monotonic() < deadline, "the primary does not see its replica"
        time.sleep(0.05)


def test_a_batch_is_on_the_replica_when_it_is_acknowledged(redis_factory):
    primary, replica = replicated_pair(redis_factory)
    store = RedisStore(primary.url("wait:"), 3600.0, wait_replicas=1, wait_timeout_ms=5000)

    async def scenario() -> None:
        await store.create(record("s1", now=time.time()), max_sessions=10)
        for seq in range(1, 6):
            current = await store.get("s1")
            assert current is not None
            updated = dataclasses.replace(current, state=f"after {seq}".encode(), last_seq=seq)
            assert await store.compare_and_set(updated, current.version)
            # acknowledged: the replica has it already, with no pause for replication
            assert (
                replica.command("HGET", "wait:session:s1", "version")
                == f"${len(str(seq))}\r\n{seq}\r\n".encode()
            )
        await store.close()

    asyncio.run(scenario())


def test_without_its_replica_a_batch_is_not_acknowledged_until_the_replica_is_back(redis_factory):
    primary, replica = replicated_pair(redis_factory)
    waiting = RedisStore(primary.url("wait:"), 3600.0, wait_replicas=1, wait_timeout_ms=200)
    not_waiting = RedisStore(primary.url("wait:"), 3600.0)

    async def scenario() -> None:
        await waiting.create(record("s1", now=time.time()), max_sessions=10)
        replica.stop()
        current = await waiting.get("s1")
        assert current is not None
        updated = dataclasses.replace(current, state=b"after 1", last_seq=1)
        started = time.monotonic()
        with pytest.raises(NotReplicated, match=r"reached 0 of the 1 replica\(s\).*within 200 ms"):
            await waiting.compare_and_set(updated, current.version)
        assert time.monotonic() - started < 3.0  # bounded by the timeout, not hanging
        stored = await waiting.get("s1")
        assert stored is not None and stored.last_seq == 1  # it is on the primary: a retry is a replay
        with pytest.raises(NotReplicated):
            await waiting.make_durable("s1")  # and that replay is not acknowledged either
        # the default (no WAIT) acknowledges on the primary alone
        again = dataclasses.replace(stored, state=b"after 2", last_seq=2)
        assert await not_waiting.compare_and_set(again, stored.version)

        replica.start()  # resynchronises from the primary
        wait_for_link(primary, replica)
        await waiting.make_durable("s1")  # now the replay can be acknowledged
        assert replica.command("HGET", "wait:session:s1", "last_seq") == b"$1\r\n2\r\n"
        await waiting.close()
        await not_waiting.close()

    asyncio.run(scenario())


def test_waiting_for_replicas_needs_redis():
    with pytest.raises(ValueError, match="needs a Redis store"):
        open_store("memory", 60.0, wait_replicas=1)
