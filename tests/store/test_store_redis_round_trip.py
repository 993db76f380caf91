"""One round trip without redis-py's pipeline object (store.redis_round_trip), against a real redis-server:
the replies in order with an error reply in its place, the connection back in the pool and still in step
after an error, a script the server lost loaded again, and a connection the server dropped replaced; the
connections kept between round trips: reused without the pool, given back to it after a failed exchange or
beyond their limit, and replaced when the server dropped them."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from edgepos.store import redis_round_trip
from edgepos.store.redis import RedisStore
from edgepos.store.redis_round_trip import KeptConnections, evalsha, round_trip
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import ResponseError

RedisServer = Any  # tests/store/conftest.py's RedisServer

SCRIPT = "return redis.call('INCRBY', KEYS[1], ARGV[1])"


def run(server: RedisServer, body: Any) -> Any:
    async def main() -> Any:
        store = RedisStore(server.url("rt:"), 60.0)
        client = await store._redis()
        try:
            return await body(client)
        finally:
            await store.close()

    return asyncio.run(main())


def test_replies_in_order_with_an_error_in_its_place(redis_server: RedisServer) -> None:
    async def body(client: Any) -> tuple[list[Any], list[Any], int]:
        await client.delete("rt:h", "rt:s")
        replies = await round_trip(
            client,
            [
                ("HSET", "rt:h", "a", b"\x00\xff", "b", 2),
                ("SET", "rt:s", "text"),
                ("HINCRBY", "rt:s", "f", 1),  # wrong type: an error reply
                ("HGET", "rt:h", "a"),
            ],
        )
        after = await round_trip(client, [("GET", "rt:s")])  # the connection is still in step
        return replies, after, len(client.connection_pool._in_use_connections)

    replies, after, in_use = run(redis_server, body)
    assert replies[:2] == [2, b"OK"]
    assert isinstance(replies[2], ResponseError) and "WRONGTYPE" in str(replies[2])
    assert replies[3] == b"\x00\xff"
    assert after == [b"text"]
    assert in_use == 0


def test_a_script_the_server_lost_is_loaded_again(redis_server: RedisServer) -> None:
    async def body(client: Any) -> list[Any]:
        script = client.register_script(SCRIPT)
        await client.delete("rt:n")
        first = await evalsha(client, script.sha, SCRIPT, ["rt:n"], [2])
        await client.script_flush()
        second = await evalsha(client, script.sha, SCRIPT, ["rt:n"], [3])
        return [first, second]

    assert run(redis_server, body) == [2, 5]


def test_a_script_error_is_raised(redis_server: RedisServer) -> None:
    async def body(client: Any) -> Any:
        script = client.register_script(SCRIPT)
        await client.set("rt:n", "not a number")
        return await evalsha(client, script.sha, SCRIPT, ["rt:n"], [1])

    with pytest.raises(ResponseError, match="not an integer"):
        run(redis_server, body)


def test_a_connection_the_server_dropped_is_replaced(redis_server: RedisServer) -> None:
    async def body(client: Any) -> list[Any]:
        await round_trip(client, [("SET", "rt:k", "1")])
        await client.execute_command("CLIENT", "KILL", "TYPE", "normal", "SKIPME", "no")
        return await round_trip(client, [("INCR", "rt:k"), ("GET", "rt:k")])

    assert run(redis_server, body) == [2, b"2"]


def test_a_wait_for_replicas_lengthens_the_socket_timeout_by_its_own() -> None:
    from edgepos.store.redis_cluster import RedisClusterStore
    from edgepos.store.redis_round_trip import allow_for_wait

    kwargs = {"socket_timeout": 1.0}
    allow_for_wait(kwargs, 1500)
    assert kwargs == {"socket_timeout": 2.5}
    allow_for_wait(kwargs, 0)  # no replicas waited for
    assert kwargs == {"socket_timeout": 2.5}
    unbounded: dict = {"socket_timeout": None}
    allow_for_wait(unbounded, 1500)  # no socket timeout: nothing to lengthen
    assert unbounded == {"socket_timeout": None}
    url = "redis-cluster://127.0.0.1:7000?socket_timeout=1"
    assert RedisClusterStore(url, 60.0, wait_replicas=1, wait_timeout_ms=1500).settings["client"][
        "socket_timeout"
    ] == pytest.approx(2.5)
    assert RedisClusterStore(url, 60.0).settings["client"]["socket_timeout"] == pytest.approx(1.0)


def test_a_kept_connection_serves_the_next_round_trips_without_the_pool(redis_server: RedisServer) -> None:
    async def body(client: Any) -> tuple[list[Any], int, int, int]:
        await client.delete("rt:c")
        pool = client.connection_pool
        kept = KeptConnections(pool, 2)
        checkouts = 0
        take = pool.get_connection

        async def counted() -> Any:
            nonlocal checkouts
            checkouts += 1
            return await take()

        pool.get_connection = counted
        replies = [await round_trip(client, [("INCR", "rt:c")], kept) for _ in range(5)]
        return replies, checkouts, kept.idle, len(pool._in_use_connections)

    replies, checkouts, idle, in_use = run(redis_server, body)
    assert replies == [[1], [2], [3], [4], [5]]
    assert (checkouts, idle, in_use) == (1, 1, 1)  # kept: in use to the pool


def test_a_failed_exchange_gives_its_connection_back_to_the_pool(
    redis_server: RedisServer, monkeypatch
) -> None:
    async def body(client: Any) -> tuple[int, int, list[Any]]:
        kept = KeptConnections(client.connection_pool, 2)
        await round_trip(client, [("SET", "rt:f", "1")], kept)

        async def broken(connection: Any, commands: Any) -> list[Any]:
            raise RedisConnectionError("the link broke mid-way")

        with monkeypatch.context() as patched:
            patched.setattr(redis_round_trip, "_exchange", broken)
            with pytest.raises(RedisConnectionError):
                await round_trip(client, [("GET", "rt:f")], kept)
        idle, in_use = kept.idle, len(client.connection_pool._in_use_connections)
        return idle, in_use, await round_trip(client, [("GET", "rt:f")], kept)

    assert run(redis_server, body) == (0, 0, [b"1"])


def test_kept_connections_beyond_the_limit_go_back_to_the_pool(redis_server: RedisServer) -> None:
    async def body(client: Any) -> tuple[list[Any], int, int]:
        kept = KeptConnections(client.connection_pool, 2)
        await client.delete("rt:p")
        replies = await asyncio.gather(*(round_trip(client, [("INCR", "rt:p")], kept) for _ in range(6)))
        return (
            sorted(reply for (reply,) in replies),
            kept.idle,
            len(client.connection_pool._in_use_connections),
        )

    replies, idle, in_use = run(redis_server, body)
    assert replies == [1, 2, 3, 4, 5, 6]
    assert (idle, in_use) == (2, 2)


def test_a_kept_connection_the_server_dropped_is_replaced(redis_server: RedisServer) -> None:
    async def body(client: Any) -> list[Any]:
        kept = KeptConnections(client.connection_pool, 2)
        await round_trip(client, [("SET", "rt:d", "1")], kept)
        await client.execute_command("CLIENT", "KILL", "TYPE", "normal", "SKIPME", "no")
        return await round_trip(client, [("INCR", "rt:d"), ("GET", "rt:d")], kept)

    assert run(redis_server, body) == [2, b"2"]


def test_the_store_keeps_connections_of_its_newest_pool_only(redis_server: RedisServer) -> None:
    async def body(client: Any) -> tuple[bool, bool]:
        other = RedisStore(redis_server.url("rt:"), 60.0)
        other_client = await other._redis()
        try:
            store_trips = redis_round_trip.RoundTrips()
            store_trips.keep_from(client.connection_pool)
            return (
                store_trips._kept_for(client) is not None,
                store_trips._kept_for(other_client) is None,
            )
        finally:
            await other.close()

    assert run(redis_server, body) == (True, True)
