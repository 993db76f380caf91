"""Reference stations in the SQLite store (``store.sqlite``): the ``base_stations`` table and each
station's correction window in ``base_epochs`` (primary key station and GPS time). Adding epochs, trimming
the window and deleting a station with its epochs are one ``BEGIN IMMEDIATE`` transaction each."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TypeVar

from edgepos.store.base import BaseWindow, StoredBaseStation

T = TypeVar("T")


class SQLiteBaseStations:
    """The reference-station part of the SQLite store (a base of ``SQLiteStore``, which provides the
    connection thread and the transaction helper)."""

    if TYPE_CHECKING:

        async def _run(self, fn: Callable[[sqlite3.Connection], T]) -> T: ...

        @staticmethod
        def _transaction(db: sqlite3.Connection, body: Callable[[], T]) -> T: ...

    async def add_base_station(self, station: StoredBaseStation) -> bool:
        def work(db: sqlite3.Connection) -> bool:
            cursor = db.execute(
                "INSERT OR IGNORE INTO base_stations VALUES (?, ?, ?)",
                (station.station_id, station.document, station.updated_at),
            )
            return cursor.rowcount == 1

        return await self._run(work)

    async def replace_base_station(self, station: StoredBaseStation) -> bool:
        def work(db: sqlite3.Connection) -> bool:
            cursor = db.execute(
                "UPDATE base_stations SET document = ?, updated_at = ? WHERE station_id = ?",
                (station.document, station.updated_at, station.station_id),
            )
            return cursor.rowcount == 1

        return await self._run(work)

    async def get_base_station(self, station_id: str) -> StoredBaseStation | None:
        def work(db: sqlite3.Connection) -> StoredBaseStation | None:
            row = db.execute(
                "SELECT station_id, document, updated_at FROM base_stations WHERE station_id = ?",
                (station_id,),
            ).fetchone()
            return None if row is None else StoredBaseStation(*row)

        return await self._run(work)

    async def list_base_stations(self) -> list[StoredBaseStation]:
        def work(db: sqlite3.Connection) -> list[StoredBaseStation]:
            rows = db.execute(
                "SELECT station_id, document, updated_at FROM base_stations ORDER BY station_id"
            )
            return [StoredBaseStation(*row) for row in rows]

        return await self._run(work)

    async def delete_base_station(self, station_id: str) -> bool:
        def body(db: sqlite3.Connection) -> bool:
            db.execute("DELETE FROM base_epochs WHERE station_id = ?", (station_id,))
            return db.execute("DELETE FROM base_stations WHERE station_id = ?", (station_id,)).rowcount == 1

        return await self._run(lambda db: self._transaction(db, lambda: body(db)))

    async def add_base_epochs(
        self, station_id: str, epochs: Sequence[tuple[float, str]], keep: int
    ) -> int | None:
        def body(db: sqlite3.Connection) -> int | None:
            if (
                db.execute("SELECT 1 FROM base_stations WHERE station_id = ?", (station_id,)).fetchone()
                is None
            ):
                return None
            db.executemany(
                "INSERT OR REPLACE INTO base_epochs VALUES (?, ?, ?)",
                [(station_id, float(gpst), document) for gpst, document in epochs],
            )
            db.execute(
                "DELETE FROM base_epochs WHERE station_id = ? AND gpst NOT IN "
                "(SELECT gpst FROM base_epochs WHERE station_id = ? ORDER BY gpst DESC LIMIT ?)",
                (station_id, station_id, int(keep)),
            )
            row = db.execute(
                "SELECT COUNT(*) FROM base_epochs WHERE station_id = ?", (station_id,)
            ).fetchone()
            return int(row[0])

        return await self._run(lambda db: self._transaction(db, lambda: body(db)))

    async def base_window(self, station_id: str, since: float, until: float) -> BaseWindow | None:
        def work(db: sqlite3.Connection) -> BaseWindow | None:
            row = db.execute(
                "SELECT station_id, document, updated_at FROM base_stations WHERE station_id = ?",
                (station_id,),
            ).fetchone()
            if row is None:
                return None
            before = db.execute(
                "SELECT gpst, document FROM base_epochs WHERE station_id = ? AND gpst < ? ORDER BY gpst DESC LIMIT 1",
                (station_id, since),
            ).fetchall()
            inside = db.execute(
                "SELECT gpst, document FROM base_epochs WHERE station_id = ? AND gpst >= ? AND gpst <= ? "
                "ORDER BY gpst",
                (station_id, since, until),
            ).fetchall()
            return BaseWindow(
                StoredBaseStation(*row), tuple((float(t), str(d)) for t, d in [*before, *inside])
            )

        return await self._run(work)
