"""Commands packed in C (store.redis_packing): the same bytes as redis-py's own packer for every argument
the store sends, the same handling (sent or refused) for the arguments hiredis does not take, and the
Redis store's connections, whatever the URL's scheme, packing this way against a real redis-server."""

from __future__ import annotations

import asyncio
import math
import os
import signal
from collections.abc import Callable
from typing import Any

import pytest
from edgepos.store.redis import RedisStore
from edgepos.store.redis_packing import (
    PackedConnection,
    PackedSSLConnection,
    PackedUnixConnection,
)
from hypothesis import given
from hypothesis import strategies as st
from redis.asyncio.connection import Connection
from redis.exceptions import DataError
from redis.exceptions import TimeoutError as RedisTimeoutError

RedisServer = Any  # tests/store/conftest.py's RedisServer

ARGUMENT = st.one_of(
    st.text(),
    st.binary(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
)


def packed(connection: Connection, *args: Any) -> bytes:
    return b"".join(bytes(chunk) for chunk in connection.pack_command(*args))


@given(
    name=st.sampled_from(["HSET", "EVALSHA", b"XADD", "SCRIPT LOAD", b"CLIENT SETNAME"]),
    args=st.lists(ARGUMENT),
)
def test_the_same_bytes_as_redis_pys_packer(name: str | bytes, args: list[Any]) -> None:
    assert packed(PackedConnection(), name, *args) == packed(Connection(), name, *args)


def test_a_large_value_is_packed_whole_and_alike() -> None:
    state = bytes(range(256)) * 200  # larger than redis-py's buffer cutoff, which it sends apart
    args = ("HSET", "k", "state", state, "t", 1.5, "n", 7, "text", "café")
    assert PackedConnection().pack_command(*args) == [packed(Connection(), *args)]


@pytest.mark.parametrize("value", [memoryview(b"abc"), bytearray(b"abc")])
def test_what_hiredis_does_not_take_is_packed_by_redis_py(value: memoryview | bytearray) -> None:
    assert packed(PackedConnection(), "SET", "k", value) == packed(Connection(), "SET", "k", value)


@pytest.mark.parametrize("value", [True, None, [1], math])
def test_what_redis_py_refuses_is_refused(value: object) -> None:
    with pytest.raises(DataError):
        PackedConnection().pack_command("SET", "k", value)


@pytest.mark.parametrize(
    ("scheme", "expected"),
    [
        ("redis://127.0.0.1:6379/0", PackedConnection),
        ("rediss://127.0.0.1:6379/0", PackedSSLConnection),
        ("unix:///tmp/redis.sock", PackedUnixConnection),
    ],
)
def test_the_store_connects_with_the_packing_class_of_the_urls_scheme(scheme: str, expected: type) -> None:
    client = RedisStore(scheme, 60.0)._connect()
    assert client.connection_pool.connection_class is expected


def test_values_round_trip_through_a_real_server(redis_server: RedisServer) -> None:
    values = {"text": "café ✓", "bytes": bytes(range(256)) * 40, "float": 0.1, "int": -(2**40)}

    async def round_trip() -> dict[bytes, bytes]:
        store = RedisStore(redis_server.url("packing:"), 60.0)
        client = await store._redis()
        script = client.register_script("return redis.call('HGETALL', KEYS[1])")
        await client.delete("packing:h")
        await client.hset("packing:h", mapping=values)
        raw = await script(keys=["packing:h"])  # SCRIPT LOAD: a name sent as two words
        await store.close()
        return dict(zip(raw[::2], raw[1::2]))

    stored = asyncio.run(round_trip())
    assert stored == {
        b"text": "café ✓".encode(),
        b"bytes": values["bytes"],
        b"float": b"0.1",
        b"int": str(-(2**40)).encode(),
    }


def test_a_write_is_not_a_task_of_its_own(redis_server: RedisServer, monkeypatch: pytest.MonkeyPatch) -> None:
    """redis-py bounds a write with ``asyncio.wait_for`` (on Python 3.11 a task per command); these connections
    bound it with a timeout context in the caller's task."""

    def no_wait_for(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("asyncio.wait_for called")

    async def commands() -> tuple[bool, bytes | None]:
        store = RedisStore(redis_server.url("packing:"), 60.0)
        client = await store._redis()
        monkeypatch.setattr(asyncio, "wait_for", no_wait_for)
        written = await client.set("packing:k", b"v")
        value = await client.get("packing:k")
        monkeypatch.undo()
        await store.close()
        return written, value

    assert asyncio.run(commands()) == (True, b"v")


def test_a_write_a_frozen_server_does_not_take_times_out_and_disconnects(
    redis_factory: Callable[..., RedisServer],
) -> None:
    """A server that stops reading (SIGSTOP): the write fills the socket's buffers and gives up after
    socket_timeout with redis-py's error, leaving the connection closed (its stream state is unknown)."""
    server = redis_factory("--save", "", "--appendonly", "no")
    server.start()

    async def stalled() -> tuple[str, bool, float]:
        connection = PackedConnection(host="127.0.0.1", port=server.port, socket_timeout=0.3)
        await connection.connect()
        os.kill(server.process.pid, signal.SIGSTOP)
        loop = asyncio.get_running_loop()
        started = loop.time()
        try:
            with pytest.raises(RedisTimeoutError) as raised:
                await connection.send_packed_command([b"x" * (64 << 20)])
        finally:
            os.kill(server.process.pid, signal.SIGCONT)
        return str(raised.value), connection.is_connected, loop.time() - started

    message, connected, elapsed = asyncio.run(stalled())
    assert message == "Timeout writing to socket"
    assert not connected
    assert 0.25 < elapsed < 5.0
