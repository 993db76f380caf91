"""The fix log (``store.fixlog``) of the Redis stores: a Redis stream shared by every worker of every
replica, with a counter that gives the fixes dense ids (see docs/redis.md, "The fix stream")."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Mapping, Sequence
from typing import Any

from edgepos.store.base import StoreUnavailable
from edgepos.store.fixlog import FixEvent, FixLog, Gap, NewFix, gap_between
from edgepos.store.redis import RedisStore
from edgepos.store.redis_fix_entries import entry_events, entry_size, fix_arguments


def _first_id(entry_id: bytes | str, fields: Mapping[bytes, bytes]) -> int:
    """The id of an entry's first fix."""
    text = entry_id.decode() if isinstance(entry_id, bytes) else entry_id
    return int(text.partition("-")[0]) - entry_size(fields) + 1


class RedisFixLog(FixLog):
    """The fix log as a Redis stream (``P{fixes}:entries``, one entry per run of a session's fixes:
    ``store.redis_fix_entries``; trimmed by every append to the entries holding the last ``buffer``
    fixes) with a counter giving dense ids (``P{fixes}:seq``). Appends are one script call on the
    store's connection pool; blocking reads use a client of their own."""

    def __init__(self, store: RedisStore, buffer: int) -> None:
        super().__init__(buffer)
        self.store = store
        self._reader: Any = None
        self._reader_loop: asyncio.AbstractEventLoop | None = None
        self._read_block_s = 0.0
        self._fixes_per_entry = 1  # in the last read: a read asks for about ``count`` fixes' worth of entries

    async def append(self, fixes: Sequence[NewFix]) -> None:
        if not fixes:
            return
        args: list[str | bytes | int] = [self.buffer, *fix_arguments(fixes)]
        store = self.store
        async with store._guard():
            client = await store._redis()
            await store._evalsha(client, "publish_fixes", [store.fixes_key, store.fixes_seq_key], args)

    async def newest(self) -> int:
        async with self.store._guard():
            value = await (await self.store._redis()).get(self.store.fixes_seq_key)
        return 0 if value is None else int(value)

    async def read(self, after: int, block_s: float, count: int) -> list[FixEvent]:
        loop = asyncio.get_running_loop()
        if self._reader is None or self._reader_loop is not loop or self._read_block_s < block_s:
            await self._close_reader()
            self._reader = self.store._blocking_client(block_s)
            self._reader_loop, self._read_block_s = loop, block_s
        try:
            # the plain store's guard (error translation) without the cluster store's pool permits
            async with RedisStore._guard(self.store):
                reply = await self._reader.xread(
                    {self.store.fixes_key: f"{after}-0"},
                    count=max(1, count // self._fixes_per_entry),
                    block=max(1, int(block_s * 1000)),
                )
        except StoreUnavailable:
            await self._close_reader()  # start afresh on a new connection
            raise
        if not reply:
            return []
        streams = reply.items() if isinstance(reply, dict) else reply  # RESP3 answers a map
        entries = [entry for _key, stream_entries in streams for entry in stream_entries]
        self._fixes_per_entry = max(1, sum(entry_size(fields) for _id, fields in entries) // len(entries))
        # the first entry may hold fixes up to ``after`` (an entry's id is its last fix's)
        events = [event for entry in entries for event in entry_events(*entry) if event.id > after]
        return events[:count]

    async def backlog(self, after: int) -> tuple[list[FixEvent], Gap | None]:
        store = self.store
        async with store._guard():
            client = await store._redis()
            pipe = client.pipeline(transaction=False)
            pipe.get(store.fixes_seq_key)
            pipe.xrange(store.fixes_key, "-", "+", count=1)
            newest_raw, first = await pipe.execute()
            newest = 0 if newest_raw is None else int(newest_raw)
            oldest = _first_id(*first[0]) if first else None
            gap = gap_between(after, oldest, newest)
            start = "-" if gap is not None else f"{after + 1}-0"  # the entry holding after + 1, onwards
            entries = await client.xrange(store.fixes_key, start, "+")  # the stream is bounded already
        events = [event for entry in entries for event in entry_events(*entry)]
        # with a gap every held event is given; else from after + 1 (the first entry may hold older ones)
        return (events if gap is not None else [event for event in events if event.id > after]), gap

    async def _close_reader(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None and self._reader_loop is asyncio.get_running_loop():
            with contextlib.suppress(Exception):
                await reader.aclose()

    async def close(self) -> None:
        await self._close_reader()
