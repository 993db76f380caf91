"""A batch's commands to one Redis server as one write and their replies, on a pooled connection, without
redis-py's pipeline object.

A batch's compare-and-set (three commands) and a fix-stream append (one script call) each went through a
redis-py pipeline or command call: a command stack, a response callback per reply, the client's retry
wrapper, observability records and, on Python 3.11, a task per write. :func:`round_trip` does what those
calls do for these commands and no more: it takes a connection from the client's pool (waiting as the
pool does), packs the commands in one write (store.redis_packing), reads one reply per command, and gives
the connection back. An error reply is returned in its place as redis-py's exception, as a pipeline
executed with ``raise_on_error=False`` returns it. A connection error or timeout disconnects the
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


async def round_trip(client: Redis, commands: Sequence[Command]) -> list[Any]:
    """The replies to ``commands``, sent together on one of ``client``'s pooled connections."""
    pool = client.connection_pool
    connection = await pool.get_connection()  # type: ignore[no-untyped-call]
    try:
        return await connection.retry.call_with_retry(  # type: ignore[no-any-return]
            lambda: _exchange(connection, commands), lambda _error: connection.disconnect()
        )
    finally:
        await pool.release(connection)


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
    client: Redis, sha: str, source: ScriptTextT, keys: Sequence[str], args: Sequence[Any]
) -> Any:
    """A script's reply by its digest, loading it first if the server lost it (restart, SCRIPT FLUSH); an
    error reply is raised, as redis-py's script objects do."""
    for _attempt in range(2):
        (reply,) = await round_trip(client, [("EVALSHA", sha, len(keys), *keys, *args)])
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
