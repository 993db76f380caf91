"""One SQLite connection used only from a thread of its own, for the asyncio code that queries it.

SQLite calls block, so they run off the event loop; one thread per database file keeps every query on
the same connection (WAL mode, a 30 s busy timeout for the other workers' writes) and in order. The
session store and the fix log each hold one, on separate files."""

from __future__ import annotations

import asyncio
import sqlite3
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


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
                self.path, timeout=30.0, isolation_level=None, check_same_thread=False
            )
            connection.execute("PRAGMA busy_timeout = 30000")
            connection.execute("PRAGMA journal_mode = WAL")
            connection.execute("PRAGMA synchronous = NORMAL")
            connection.executescript(self.schema)
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
