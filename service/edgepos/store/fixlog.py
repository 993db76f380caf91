"""The fix stream's bounded log: the last N fixes of every session, in the order they were applied.

Every applied batch appends its fixes (``GET /v1/stream/fixes`` reads them). Each event gets the next
decimal integer id of the log (dense: one more than the previous event's), so a consumer that comes
back with the id of the last event it saw gets exactly the events after it, or, when the log no longer
holds them all, a :class:`Gap` saying how many it missed. The implementations, by kind of store:

* :class:`MemoryFixLog` and ``AppendedFixLog`` (``edgepos.store.memory``, the in-process store's, which
  makes an event only when it is read): a ``deque`` in this process, for one worker;
* :class:`SQLiteFixLog`: a table in a file beside the SQLite store's, shared by the workers of one box;
* ``RedisFixLog`` (``edgepos.store.redis_fixlog``): a Redis stream, shared by every worker of every replica.

The log is written by one publisher task per worker and read by one reader task per worker (which
fans the events out to that worker's consumers), never by the requests of the vehicles themselves.
"""

from __future__ import annotations

import asyncio
import sqlite3
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from edgepos.store.sqlite_thread import SQLiteThread

T = TypeVar("T")

DEFAULT_BUFFER = 10_000


@dataclass(frozen=True)
class NewFix:
    """A fix to append: who it is of (for the consumers' filters), its time ``t`` (for decimation) and
    ``data``, the event's JSON as sent to consumers."""

    session_id: str
    vehicle_id: str
    pipeline: str
    t: float
    data: bytes


@dataclass(frozen=True)
class FixEvent:
    """A fix in the log, with its id (a decimal integer as text)."""

    id: int
    session_id: str
    vehicle_id: str
    pipeline: str
    t: float
    data: bytes


@dataclass(frozen=True)
class Gap:
    """Events after the consumer's last id that the log cannot give it.

    ``reason`` is ``trimmed`` (they were older than the buffer holds: ``missed`` of them) or ``unknown``
    (the id is ahead of the log: the log was reset, e.g. an in-process store restarted, or the id is not
    one of this log's; how many were missed is not known, ``missed`` is None)."""

    reason: str
    missed: int | None
    oldest_id: int | None


def parse_event_id(text: str) -> int:
    """A consumer's ``Last-Event-ID``: a decimal integer (``n`` or Redis's ``n-0``); ValueError otherwise."""
    head, dash, tail = text.strip().partition("-")
    if not head.isdigit() or len(head) > 19 or (dash and tail != "0"):
        raise ValueError(f"not an event id of this stream: {text[:40]!r}")
    return int(head)


def gap_between(after: int, oldest: int | None, newest: int) -> Gap | None:
    """The gap a consumer whose last event was ``after`` has, when the log holds ``oldest``..``newest``
    (``oldest`` None: it holds nothing) and ``newest`` is the last id it ever gave."""
    if after > newest:
        return Gap("unknown", None, oldest)
    first = newest + 1 if oldest is None else oldest
    if after < first - 1:
        return Gap("trimmed", first - 1 - after, oldest)
    return None


class FixLog(ABC):
    """The bounded log of fixes (``buffer`` events)."""

    def __init__(self, buffer: int = DEFAULT_BUFFER) -> None:
        if buffer < 1:
            raise ValueError("the fix stream buffer must hold at least one event")
        self.buffer = int(buffer)

    @abstractmethod
    async def append(self, fixes: Sequence[NewFix]) -> None:
        """Append ``fixes`` in order (the oldest events beyond ``buffer`` are dropped)."""

    @abstractmethod
    async def newest(self) -> int:
        """The id of the newest event ever appended (0 when none): where a live reader starts."""

    @abstractmethod
    async def read(self, after: int, block_s: float, count: int) -> list[FixEvent]:
        """Up to ``count`` events with ids above ``after``, oldest first, waiting up to ``block_s`` for
        one when there is none yet (then an empty list)."""

    @abstractmethod
    async def backlog(self, after: int) -> tuple[list[FixEvent], Gap | None]:
        """Every held event after ``after`` (all held ones when there is a gap), and the gap if any."""

    def append_now(self, fixes: Sequence[NewFix]) -> bool:
        """Append ``fixes`` at once, if this log can without waiting (one in this process's memory), and
        say so; False leaves them to :meth:`append`."""
        return False

    async def close(self) -> None:
        return


class LocalFixLog(FixLog):
    """A log in this process's memory: ids counted here, and a blocking read that waits for the next
    append. Subclasses keep the events and find those after an id (``_after``)."""

    def __init__(self, buffer: int = DEFAULT_BUFFER) -> None:
        super().__init__(buffer)
        self._newest = 0
        self._appended: asyncio.Event | None = None

    def _appended_now(self) -> None:
        """Wake the readers waiting for an append."""
        if self._appended is not None:
            self._appended.set()
            self._appended = None

    @abstractmethod
    def _after(self, after: int, count: int) -> list[FixEvent]:
        """Up to ``count`` held events with ids above ``after``, oldest first."""

    async def newest(self) -> int:
        return self._newest

    async def read(self, after: int, block_s: float, count: int) -> list[FixEvent]:
        found = self._after(after, count)
        if found or block_s <= 0:
            return found
        if self._appended is None:
            self._appended = asyncio.Event()
        try:
            await asyncio.wait_for(self._appended.wait(), block_s)
        except TimeoutError:
            return []
        return self._after(after, count)


class MemoryFixLog(LocalFixLog):
    """The log in this process, an event per fix: right for a store that serves one worker only."""

    def __init__(self, buffer: int = DEFAULT_BUFFER) -> None:
        super().__init__(buffer)
        self._events: deque[FixEvent] = deque(maxlen=self.buffer)

    async def append(self, fixes: Sequence[NewFix]) -> None:
        for fix in fixes:
            self._newest += 1
            self._events.append(
                FixEvent(self._newest, fix.session_id, fix.vehicle_id, fix.pipeline, fix.t, fix.data)
            )
        if fixes:
            self._appended_now()

    def _after(self, after: int, count: int) -> list[FixEvent]:
        if not self._events or after >= self._newest:
            return []
        start = max(0, after + 1 - self._events[0].id)
        return [self._events[i] for i in range(start, min(len(self._events), start + count))]

    async def backlog(self, after: int) -> tuple[list[FixEvent], Gap | None]:
        gap = gap_between(after, self._events[0].id if self._events else None, self._newest)
        return self._after(-1 if gap is not None else after, self.buffer), gap


_SCHEMA = """
CREATE TABLE IF NOT EXISTS fixes (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    session_id TEXT NOT NULL,
    vehicle_id TEXT NOT NULL,
    pipeline TEXT NOT NULL,
    t REAL NOT NULL,
    data BLOB NOT NULL
);
"""

POLL_S = 0.05
"""How often a SQLite reader looks for new events while it waits (the file has no notification)."""


def fix_log_path(store_path: Path) -> Path:
    """The SQLite fix log's file: beside the store's, so that its writes never hold the lock of the
    sessions' file (a session's compare-and-set never waits for a fix being logged)."""
    return store_path.with_name(store_path.name + "-fixes")


class SQLiteFixLog(FixLog):
    """The log as a table in its own SQLite file (WAL), shared by the workers of one box; ids are the
    table's AUTOINCREMENT keys. Readers poll every :data:`POLL_S` while they wait."""

    def __init__(self, path: Path, buffer: int = DEFAULT_BUFFER) -> None:
        super().__init__(buffer)
        self.path = Path(path)
        self._database = SQLiteThread(self.path, _SCHEMA, "edgepos-fixlog")

    async def _run(self, fn: Callable[[sqlite3.Connection], T]) -> T:
        return await self._database.run(fn)

    @staticmethod
    def _newest(db: sqlite3.Connection) -> int:
        row = db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'fixes'").fetchone()
        return 0 if row is None else int(row[0])

    async def append(self, fixes: Sequence[NewFix]) -> None:
        rows = [(f.session_id, f.vehicle_id, f.pipeline, f.t, f.data) for f in fixes]
        if not rows:
            return

        def work(db: sqlite3.Connection) -> None:
            db.execute("BEGIN IMMEDIATE")
            try:
                db.executemany(
                    "INSERT INTO fixes (session_id, vehicle_id, pipeline, t, data) VALUES (?, ?, ?, ?, ?)",
                    rows,
                )
                db.execute("DELETE FROM fixes WHERE id <= ?", (self._newest(db) - self.buffer,))
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise

        await self._run(work)

    async def newest(self) -> int:
        return await self._run(self._newest)

    @staticmethod
    def _select(db: sqlite3.Connection, after: int, count: int) -> list[FixEvent]:
        rows = db.execute(
            "SELECT id, session_id, vehicle_id, pipeline, t, data FROM fixes WHERE id > ? ORDER BY id LIMIT ?",
            (after, count),
        ).fetchall()
        return [FixEvent(int(r[0]), r[1], r[2], r[3], float(r[4]), bytes(r[5])) for r in rows]

    async def read(self, after: int, block_s: float, count: int) -> list[FixEvent]:
        deadline = time.monotonic() + block_s
        while True:
            found = await self._run(lambda db: self._select(db, after, count))
            if found or time.monotonic() >= deadline:
                return found
            await asyncio.sleep(POLL_S)

    async def backlog(self, after: int) -> tuple[list[FixEvent], Gap | None]:
        def work(db: sqlite3.Connection) -> tuple[list[FixEvent], Gap | None]:
            db.execute("BEGIN")  # one snapshot for the bounds and the events
            try:
                oldest = db.execute("SELECT MIN(id) FROM fixes").fetchone()[0]
                gap = gap_between(after, None if oldest is None else int(oldest), self._newest(db))
                return self._select(db, -1 if gap is not None else after, self.buffer), gap
            finally:
                db.execute("COMMIT")

        return await self._run(work)

    async def close(self) -> None:
        await self._database.close()
