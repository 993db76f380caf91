"""Commands packed in C on the Redis store's connections.

redis-py's asyncio connection packs every command in Python, one encode call and a few joins per
argument; a batch sends some 150 arguments (the record's hash fields, the fix stream's entries), and
that packing was the largest share of the worker's CPU on the Redis path (docs/benchmarks.md, "Redis:
commands packed in C"). ``hiredis.pack_command`` writes the same bytes in one C call. It takes str,
bytes, int and float (encoded as redis-py's encoder does: UTF-8, ``repr`` of numbers); anything else
(a memoryview, a bool, None) goes to redis-py's own packer, so it is sent, or refused, as before.
"""

from __future__ import annotations

from typing import Any

import hiredis
from redis.asyncio.connection import (
    AbstractConnection,
    Connection,
    SSLConnection,
    UnixDomainSocketConnection,
)


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
