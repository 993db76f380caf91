"""A batch's commands to one Redis server as one write and their replies, on a pooled connection, without
redis-py's pipeline object.

A batch's compare-and-set (three commands) and a fix-stream append (one script call) each went through a
redis-py pipeline or command call: a command stack, a response callback per reply, the client's retry
wrapper, observability records and, on Python 3.11, a task per write. :func:`round_trip` does what those
calls do for these commands and no more: it takes a connection from the client's pool (waiting as the
pool does), packs the commands in one write (store.redis_packing), reads one reply per command, and gives
the connection back (or keeps it for the next round trip: :class:`KeptConnections`). An error reply is
returned in its place as redis-py's exception, as a pipeline executed with ``raise_on_error=False`` returns it. A connection error or timeout disconnects the
connection and the whole round trip is tried again as the connection's retry policy allows (the store's:
once), as redis-py's pipeline does; the store only sends commands that are safe to repeat (a staged hash
under a fresh key, a compare-and-set, a fix append whose ids come from the server's counter).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from redis.asyncio import Redis
from redis.exceptions import NoScriptError, ResponseError
from redis.typing import ScriptTextT

Command = Sequence[Any]


class KeptConnections:
    """Connections of one client's pool kept between round trips, at most ``limit`` of them idle.

    Taking a connection from redis-py's blocking pool and giving it back costs the event loop about 30 µs a
    round trip (its condition and timeout, a readiness test of the socket, its observability events): a
    third of a batch's compare-and-set. A connection whose exchange ended cleanly, every reply read, is in
    step for the next one as it is, and waits here. One whose exchange failed or was cancelled mid-way goes
    back to the pool, whose next checkout tests it and reconnects it if need be. A kept connection the server
    dropped meanwhile (a restart) is met by the connection's retry policy, a reconnect and one more try, as
    a pooled one gone stale is. Kept connections count as in use to the pool, so ``limit`` stays a fraction
    of its size."""

    SHARE = 4
    """At most a quarter of a pool's connections wait idle here (``of_pool``)."""

    def __init__(self, pool: Any, limit: int) -> None:
        self.pool = pool
        self.limit = limit
        self._idle: list[Any] = []

    @classmethod
    def of_pool(cls, pool: Any) -> KeptConnections:
        """Kept connections of ``pool``, at most a ``SHARE``-th of its size idle."""
        return cls(pool, max(1, int(pool.max_connections) // cls.SHARE))

    async def take(self) -> Any:
        """A kept connection, or one from the pool (waiting as the pool does)."""
        return self._idle.pop() if self._idle else await self.pool.get_connection()

    async def give_back(self, connection: Any, clean: bool) -> None:
        """Keep ``connection`` if its exchange ended ``clean`` and there is room, else return it to the pool."""
        if clean and len(self._idle) < self.limit:
            self._idle.append(connection)
        else:
            await self.pool.release(connection)

    @property
    def idle(self) -> int:
        return len(self._idle)


async def round_trip(
    client: Redis, commands: Sequence[Command], kept: KeptConnections | None = None
) -> list[Any]:
    """The replies to ``commands``, sent together on one of ``client``'s pooled connections (one of
    ``kept``'s, when given: it must hold connections of ``client``'s pool)."""
    pool = client.connection_pool
    connection = await (pool.get_connection() if kept is None else kept.take())  # type: ignore[no-untyped-call]
    clean = False
    try:
        replies: list[Any] = await connection.retry.call_with_retry(
            lambda: _exchange(connection, commands), lambda _error: connection.disconnect()
        )
        clean = True
        return replies
    finally:
        if kept is None:
            await pool.release(connection)
        else:
            await kept.give_back(connection, clean)


async def _exchange(connection: Any, commands: Sequence[Command]) -> list[Any]:
    await connection.send_packed_command(connection.pack_commands(commands))
    replies: list[Any] = []
    for _ in commands:
        try:
            replies.append(await connection.read_response())
        except ResponseError as error:  # read in full all the same: the connection stays in step
            replies.append(error)
    return replies


async def evalsha(
    client: Redis,
    sha: str,
    source: ScriptTextT,
    keys: Sequence[str],
    args: Sequence[Any],
    kept: KeptConnections | None = None,
) -> Any:
    """A script's reply by its digest, loading it first if the server lost it (restart, SCRIPT FLUSH); an
    error reply is raised, as redis-py's script objects do."""
    for _attempt in range(2):
        (reply,) = await round_trip(client, [("EVALSHA", sha, len(keys), *keys, *args)], kept)
        if isinstance(reply, NoScriptError):
            await client.script_load(source)
            continue
        if isinstance(reply, Exception):
            raise reply
        return reply
    raise NoScriptError("Redis kept losing the script")


def allow_for_wait(connection_kwargs: dict[str, Any], wait_timeout_ms: int) -> None:
    """Lengthen a pool's socket timeout by ``wait_timeout_ms``: a batch's write ends with WAIT, which answers
    only after that long when a replica is missing, and a shorter socket timeout would cut it off as a
    server that does not answer (a 503 that blames the store instead of the replica, and a retry)."""
    timeout = connection_kwargs.get("socket_timeout")
    if wait_timeout_ms > 0 and timeout is not None:
        connection_kwargs["socket_timeout"] = float(timeout) + wait_timeout_ms / 1000.0


class RoundTrips:
    """A store's round trips and script calls, on connections kept between them (:class:`KeptConnections`)
    for the pool it named last (its newest client's); a client of another pool takes the pool's own way."""

    def __init__(self) -> None:
        self._kept: KeptConnections | None = None

    def keep_from(self, pool: Any) -> None:
        """Keep connections of ``pool`` from now on (those kept from an earlier pool close with it)."""
        self._kept = KeptConnections.of_pool(pool)

    def _kept_for(self, client: Redis) -> KeptConnections | None:
        kept = self._kept
        return kept if kept is not None and kept.pool is client.connection_pool else None

    async def run(self, client: Redis, commands: Sequence[Command]) -> list[Any]:
        """:func:`round_trip`."""
        return await round_trip(client, commands, self._kept_for(client))

    async def evalsha(
        self, client: Redis, sha: str, source: ScriptTextT, keys: Sequence[str], args: Sequence[Any]
    ) -> Any:
        """:func:`evalsha`."""
        return await evalsha(client, sha, source, keys, args, self._kept_for(client))
