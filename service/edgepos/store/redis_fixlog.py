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
from edgepos.store.redis_records import fix_arguments


def _entry_event(entry_id: bytes | str, fields: Mapping[bytes, bytes]) -> FixEvent:
    text = entry_id.decode() if isinstance(entry_id, bytes) else entry_id
    return FixEvent(
        int(text.partition("-")[0]),
        fields[b"s"].decode(),
        fields[b"v"].decode(),
        fields[b"p"].decode(),
        float(fields[b"t"]),
        bytes(fields[b"d"]),
    )


class RedisFixLog(FixLog):
    """The fix log as a Redis stream (``P{fixes}:stream``, trimmed to about ``buffer`` entries by every
    append) with a counter giving dense ids (``P{fixes}:seq``). Appends are one script call on the
    store's connection pool; blocking reads use a client of their own."""

    def __init__(self, store: RedisStore, buffer: int) -> None:
        super().__init__(buffer)
        self.store = store
        self._reader: Any = None
        self._reader_loop: asyncio.AbstractEventLoop | None = None
        self._read_block_s = 0.0

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
                    {self.store.fixes_key: f"{after}-0"}, count=count, block=max(1, int(block_s * 1000))
                )
        except StoreUnavailable:
            await self._close_reader()  # start afresh on a new connection
            raise
        if not reply:
            return []
        streams = reply.items() if isinstance(reply, dict) else reply  # RESP3 answers a map
        return [_entry_event(entry_id, fields) for _key, entries in streams for entry_id, fields in entries]

    async def backlog(self, after: int) -> tuple[list[FixEvent], Gap | None]:
        store = self.store
        async with store._guard():
            client = await store._redis()
            pipe = client.pipeline(transaction=False)
            pipe.get(store.fixes_seq_key)
            pipe.xrange(store.fixes_key, "-", "+", count=1)
            newest_raw, first = await pipe.execute()
            newest = 0 if newest_raw is None else int(newest_raw)
            oldest = _entry_event(*first[0]).id if first else None
            gap = gap_between(after, oldest, newest)
            start = "-" if gap is not None else f"{after + 1}-0"
            entries = await client.xrange(store.fixes_key, start, "+")  # the stream is bounded already
        return [_entry_event(entry_id, fields) for entry_id, fields in entries], gap

    async def _close_reader(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None and self._reader_loop is asyncio.get_running_loop():
            with contextlib.suppress(Exception):
                await reader.aclose()

    async def close(self) -> None:
        await self._close_reader()
