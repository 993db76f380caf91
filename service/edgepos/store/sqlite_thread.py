"""One SQLite connection used only from a thread of its own, for the asyncio code that queries it.

SQLite calls block, so they run off the event loop; one thread per database file keeps every query on
the same connection (WAL mode, a 30 s busy timeout for the other workers' writes, the set-up tried again
while another connection holds the file locked) and in order. The
session store and the fix log each hold one, on separate files."""

from __future__ import annotations

import asyncio
import sqlite3
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

BUSY_TIMEOUT_S = 30.0
"""How long a connection waits for another's lock (the other workers' writes) before it gives up."""


def set_up(connection: sqlite3.Connection, schema: str, clock: Callable[[], float] = time.monotonic) -> None:
    """WAL mode, NORMAL synchronous and ``schema`` on a new connection, tried again while the database is
    locked, up to ``BUSY_TIMEOUT_S``. Switching a file to WAL takes an exclusive lock, and SQLite may
    answer "database is locked" at once instead of calling the busy handler, as it did when several
    workers opened a new file together (the store contract's concurrent creates, once in CI); so the
    mode is set only when it is not WAL already, and a locked attempt is retried after a short sleep."""
    deadline = clock() + BUSY_TIMEOUT_S
    pause = 0.005
    while True:
        try:
            connection.execute(f"PRAGMA busy_timeout = {int(BUSY_TIMEOUT_S * 1000)}")
            if str(connection.execute("PRAGMA journal_mode").fetchone()[0]).lower() != "wal":
                connection.execute("PRAGMA journal_mode = WAL")
            connection.execute("PRAGMA synchronous = NORMAL")
            connection.executescript(schema)
            return
        except sqlite3.OperationalError as error:
            if "locked" not in str(error) and "busy" not in str(error):
                raise
            if clock() + pause > deadline:
                raise
        time.sleep(pause)
        pause = min(2 * pause, 0.2)


class SQLiteThread:
    """A lazily opened connection to ``path`` (its ``schema`` applied on opening) and the one thread
    that uses it."""

    def __init__(self, path: Path, schema: str, thread_name: str) -> None:
        self.path = path
        self.schema = schema
        self.thread_name = thread_name
        self._executor: ThreadPoolExecutor | None = None
        self._connection: sqlite3.Connection | None = None

    def _connect(self) -> sqlite3.Connection:
        if self._connection is None:
            if self.path.parent != Path(""):
                self.path.parent.mkdir(parents=True, exist_ok=True)
            connection = sqlite3.connect(
                self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None, check_same_thread=False
            )
            try:
                set_up(connection, self.schema)
            except BaseException:
                connection.close()
                raise
            self._connection = connection
        return self._connection

    async def run(self, fn: Callable[[sqlite3.Connection], T]) -> T:
        """``fn(connection)`` on the thread, opening the connection on first use."""
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=self.thread_name)
        return await asyncio.get_running_loop().run_in_executor(self._executor, lambda: fn(self._connect()))

    async def close(self) -> None:
        """Close the connection and stop the thread; a later ``run`` reopens both."""
        executor, self._executor = self._executor, None
        if executor is None:
            return

        def work() -> None:
            if self._connection is not None:
                self._connection.close()
                self._connection = None

        await asyncio.get_running_loop().run_in_executor(executor, work)
        executor.shutdown(wait=True)
