"""Commands packed in C on the Redis store's connections.

redis-py's asyncio connection packs every command in Python, one encode call and a few joins per
argument; a batch sends some 150 arguments (the record's hash fields, the fix stream's entries), and
that packing was the largest share of the worker's CPU on the Redis path (docs/benchmarks.md, "Redis:
commands packed in C"). ``hiredis.pack_command`` writes the same bytes in one C call. It takes str,
bytes, int and float (encoded as redis-py's encoder does: UTF-8, ``repr`` of numbers); anything else
(a memoryview, a bool, None) goes to redis-py's own packer, so it is sent, or refused, as before.

The same connections also write a packed command under a timeout context instead of redis-py's
``asyncio.wait_for``, which on Python 3.11 runs the write in a task of its own (a task, a timer and a
loop iteration per command sent); the write, its timeout and its errors are redis-py's.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import Any

import hiredis
from redis.asyncio.connection import (
    AbstractConnection,
    Connection,
    SSLConnection,
    UnixDomainSocketConnection,
)
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError

# the timeout context redis-py's reads use (asyncio's has a known bug before 3.11.3: redis/redis-py#2633)
if sys.version_info >= (3, 11, 3):
    from asyncio import timeout as async_timeout
else:
    from async_timeout import timeout as async_timeout


class HiredisPacking(AbstractConnection):
    """Packs a command with ``hiredis.pack_command`` (a mixin before one of redis-py's connection classes)."""

    def pack_command(self, *args: Any) -> list[bytes]:
        # as redis-py does: a command name holding spaces ('SCRIPT LOAD') is sent as several words
        name = args[0]
        if isinstance(name, str):
            args = (*name.encode().split(), *args[1:])
        elif b" " in name:
            args = (*name.split(), *args[1:])
        try:
            return [hiredis.pack_command(args)]
        except TypeError:
            return super().pack_command(*args)

    async def send_packed_command(
        self, command: bytes | str | Iterable[bytes], check_health: bool = True
    ) -> None:
        """redis-py's ``send_packed_command`` with the write bounded by ``async_timeout`` (as its reads
        are) rather than by ``asyncio.wait_for``: the same write, timeout, errors and disconnects."""
        if not self.is_connected:
            await self.connect_check_health(check_health=False)
        if check_health:
            await self.check_health()  # type: ignore[no-untyped-call]
        try:
            if isinstance(command, str):
                command = command.encode()
            if isinstance(command, bytes):
                command = [command]
            writer: Any = self._writer  # set by the connect above
            if self.socket_timeout:
                async with async_timeout(self.socket_timeout):
                    writer.writelines(command)
                    await writer.drain()
            else:
                writer.writelines(command)
                await writer.drain()
        except TimeoutError:  # asyncio's, from the timeout context
            await self.disconnect(nowait=True)
            raise RedisTimeoutError("Timeout writing to socket") from None
        except OSError as error:
            await self.disconnect(nowait=True)
            err_no, message = ("UNKNOWN", error.args[0]) if len(error.args) == 1 else error.args[:2]
            raise RedisConnectionError(f"Error {err_no} while writing to socket. {message}.") from error
        except BaseException:
            # a write cut short (cancelled, timed out): the connection's stream is unknown, as in redis-py
            await self.disconnect(nowait=True)
            raise


class PackedConnection(HiredisPacking, Connection):
    """A TCP connection (``redis://``) packing in C."""


class PackedSSLConnection(HiredisPacking, SSLConnection):
    """A TLS connection (``rediss://``) packing in C."""


class PackedUnixConnection(HiredisPacking, UnixDomainSocketConnection):
    """A Unix socket connection (``unix://``) packing in C."""


PACKED: dict[type[AbstractConnection], type[AbstractConnection]] = {
    Connection: PackedConnection,
    SSLConnection: PackedSSLConnection,
    UnixDomainSocketConnection: PackedUnixConnection,
}
"""The packing class for each connection class redis-py picks from a URL's scheme."""
