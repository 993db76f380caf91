"""The location adapter's documents and the leases in the SQLite store (``store.sqlite``): the
``documents`` table (primary key kind and key) and the ``leases`` table, each operation one statement."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

T = TypeVar("T")


class SQLiteDocuments:
    """Documents and leases of the SQLite store (a base of ``SQLiteStore``, which provides the connection
    thread and the clock)."""

    if TYPE_CHECKING:
        clock: Callable[[], float]

        async def _run(self, fn: Callable[[sqlite3.Connection], T]) -> T: ...

    async def put_document(self, kind: str, key: str, text: str) -> None:
        def work(db: sqlite3.Connection) -> None:
            db.execute("INSERT OR REPLACE INTO documents VALUES (?, ?, ?)", (kind, key, text))

        await self._run(work)

    async def replace_document(self, kind: str, key: str, text: str) -> bool:
        def work(db: sqlite3.Connection) -> bool:
            cursor = db.execute("UPDATE documents SET text = ? WHERE kind = ? AND key = ?", (text, kind, key))
            return cursor.rowcount == 1

        return await self._run(work)

    async def get_document(self, kind: str, key: str) -> str | None:
        def work(db: sqlite3.Connection) -> str | None:
            row = db.execute("SELECT text FROM documents WHERE kind = ? AND key = ?", (kind, key)).fetchone()
            return None if row is None else str(row[0])

        return await self._run(work)

    async def list_documents(self, kind: str) -> dict[str, str]:
        def work(db: sqlite3.Connection) -> dict[str, str]:
            rows = db.execute("SELECT key, text FROM documents WHERE kind = ? ORDER BY key", (kind,))
            return {str(key): str(text) for key, text in rows}

        return await self._run(work)

    async def delete_document(self, kind: str, key: str) -> bool:
        def work(db: sqlite3.Connection) -> bool:
            return db.execute("DELETE FROM documents WHERE kind = ? AND key = ?", (kind, key)).rowcount == 1

        return await self._run(work)

    async def acquire_lease(self, name: str, owner: str, ttl_s: float) -> bool:
        now = self.clock()

        def work(db: sqlite3.Connection) -> bool:
            # One statement: the row is taken when absent, expired or already the owner's, atomically.
            cursor = db.execute(
                "INSERT INTO leases VALUES (?, ?, ?) ON CONFLICT (name) DO UPDATE SET owner = excluded.owner, "
                "expires_at = excluded.expires_at WHERE leases.owner = excluded.owner OR leases.expires_at <= ?",
                (name, owner, now + ttl_s, now),
            )
            return cursor.rowcount == 1

        return await self._run(work)
