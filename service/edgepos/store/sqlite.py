"""A store in one SQLite file (WAL mode), shared by several worker processes on one box.

Each process talks to the file through one connection owned by one background thread, so the
event loop never blocks on disk. Writers coordinate through SQLite's own locking; session updates
are compare-and-set on ``version``, so when two workers race on one session exactly one wins and
the other reloads and retries. Writes that touch several tables (creating a session, which may
supersede the vehicle's previous one; deleting a session or a vehicle; rotating a vehicle's key) are
one ``BEGIN IMMEDIATE`` transaction each, so no worker ever sees half of one.

The vehicle's live-session pointer (``live_sessions``) is removed with its session by every write
that removes sessions; readers also treat a pointer to a missing or expired session as absent.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from edgepos.pipelines.base import NeighbourTrack, Rsu
from edgepos.store.base import (
    Clock,
    Revocation,
    SessionRecord,
    SessionStore,
    SessionSummary,
    StoredEphemerides,
    Supersession,
    TooManySessions,
    VehicleNotRegistered,
    VehicleRecord,
    decode_track,
    encode_track,
    refuse_fixes_in_write,
)
from edgepos.store.fixlog import FixLog, NewFix, SQLiteFixLog, fix_log_path
from edgepos.store.ratelimit import RateLimit, gcra
from edgepos.store.sqlite_base import SQLiteBaseStations
from edgepos.store.sqlite_documents import SQLiteDocuments
from edgepos.store.sqlite_thread import SQLiteThread

T = TypeVar("T")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    session_id TEXT PRIMARY KEY,
    vehicle_id TEXT NOT NULL,
    pipeline TEXT NOT NULL,
    options TEXT NOT NULL,
    token_hash TEXT NOT NULL,
    state BLOB NOT NULL,
    created_at REAL NOT NULL,
    updated_at REAL NOT NULL,
    last_seq INTEGER NOT NULL,
    last_request_hash TEXT,
    last_response BLOB,
    batches INTEGER NOT NULL,
    epochs INTEGER NOT NULL,
    last_fix TEXT,
    version INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS sessions_updated_at ON sessions (updated_at);
CREATE TABLE IF NOT EXISTS rsus (
    id TEXT PRIMARY KEY,
    x REAL NOT NULL,
    y REAL NOT NULL,
    range_std REAL,
    bearing_std REAL,
    radius REAL
);
CREATE TABLE IF NOT EXISTS ephemerides (
    slot INTEGER PRIMARY KEY CHECK (slot = 0),
    digest TEXT NOT NULL,
    text TEXT NOT NULL,
    uploaded_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS base_stations (
    station_id TEXT PRIMARY KEY,
    document TEXT NOT NULL,
    updated_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS base_epochs (
    station_id TEXT NOT NULL,
    gpst REAL NOT NULL,
    document TEXT NOT NULL,
    PRIMARY KEY (station_id, gpst)
);
CREATE TABLE IF NOT EXISTS tracks (
    vehicle_id TEXT PRIMARY KEY,
    written_at REAL NOT NULL,
    track TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS rate_limits (
    key TEXT PRIMARY KEY,
    tat REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS vehicles (
    vehicle_id TEXT PRIMARY KEY,
    key_hash TEXT NOT NULL UNIQUE,
    created_at REAL NOT NULL,
    key_issued_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS live_sessions (
    vehicle_id TEXT PRIMARY KEY,
    session_id TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS live_sessions_session_id ON live_sessions (session_id);
CREATE TABLE IF NOT EXISTS supersessions (
    session_id TEXT PRIMARY KEY,
    superseded_by TEXT NOT NULL,
    token_hash TEXT NOT NULL,
    at REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS supersessions_at ON supersessions (at);
CREATE TABLE IF NOT EXISTS documents (
    kind TEXT NOT NULL,
    key TEXT NOT NULL,
    text TEXT NOT NULL,
    PRIMARY KEY (kind, key)
);
CREATE TABLE IF NOT EXISTS leases (
    name TEXT PRIMARY KEY,
    owner TEXT NOT NULL,
    expires_at REAL NOT NULL
);
"""

_SESSION_COLUMNS = (
    "session_id, vehicle_id, pipeline, options, token_hash, state, created_at, updated_at, last_seq, "
    "last_request_hash, last_response, batches, epochs, last_fix, version"
)
_SUMMARY_COLUMNS = (
    "session_id, vehicle_id, pipeline, created_at, updated_at, last_seq, batches, epochs, last_fix"
)
_VEHICLE_COLUMNS = "vehicle_id, key_hash, created_at, key_issued_at"

# The vehicle's live session: its pointer, only while the session it names exists and is not expired.
_LIVE_SESSION = (
    "SELECT l.session_id FROM live_sessions AS l JOIN sessions AS s ON s.session_id = l.session_id "
    "WHERE l.vehicle_id = ? AND s.updated_at >= ?"
)


def path_from_url(url: str) -> Path:
    """``sqlite:///relative.db`` or ``sqlite:////absolute/path.db`` -> the file's path."""
    prefix = "sqlite:///"
    if not url.startswith(prefix) or len(url) == len(prefix):
        raise ValueError(f"not a SQLite store URL (want sqlite:///path.db): {url!r}")
    return Path(url[len(prefix) :])


class SQLiteStore(SQLiteBaseStations, SQLiteDocuments, SessionStore):
    """Sessions and RSUs in a SQLite database file."""

    def __init__(self, path: str | Path, ttl_s: float, clock: Clock = time.time) -> None:
        super().__init__(ttl_s, clock)
        self.path = Path(path)
        self._database = SQLiteThread(self.path, _SCHEMA, "edgepos-sqlite")

    def fix_log(self, buffer: int) -> FixLog:
        """The fix stream's log in a file beside this one (see ``edgepos.store.fixlog``)."""
        return SQLiteFixLog(fix_log_path(self.path), buffer)

    async def _run(self, fn: Callable[[sqlite3.Connection], T]) -> T:
        return await self._database.run(fn)

    @staticmethod
    def _record(row: tuple[Any, ...]) -> SessionRecord:
        (
            sid,
            vehicle,
            pipeline,
            options,
            token_hash,
            state,
            created,
            updated,
            last_seq,
            req_hash,
            response,
            batches,
            epochs,
            last_fix,
            version,
        ) = row
        return SessionRecord(
            session_id=sid,
            vehicle_id=vehicle,
            pipeline=pipeline,
            options=json.loads(options),
            token_hash=token_hash,
            state=bytes(state),
            created_at=created,
            updated_at=updated,
            last_seq=last_seq,
            last_request_hash=req_hash,
            last_response=None if response is None else bytes(response),
            batches=batches,
            epochs=epochs,
            last_fix=last_fix,
            version=version,
        )

    @staticmethod
    def _row(record: SessionRecord) -> tuple[Any, ...]:
        return (
            record.session_id,
            record.vehicle_id,
            record.pipeline,
            json.dumps(record.options, allow_nan=False),
            record.token_hash,
            record.state,
            record.created_at,
            record.updated_at,
            record.last_seq,
            record.last_request_hash,
            record.last_response,
            record.batches,
            record.epochs,
            record.last_fix,
            record.version,
        )

    def _live_since(self) -> float:
        return self.clock() - self.ttl_s

    @staticmethod
    def _transaction(db: sqlite3.Connection, body: Callable[[], T]) -> T:
        """``body`` inside one ``BEGIN IMMEDIATE`` transaction (the write lock is taken up front, so
        what it reads cannot change before it writes); rolled back if it raises."""
        db.execute("BEGIN IMMEDIATE")
        try:
            result = body()
        except BaseException:
            db.execute("ROLLBACK")
            raise
        db.execute("COMMIT")
        return result

    def _purge_expired(self, db: sqlite3.Connection) -> int:
        """Delete expired sessions and the live-session pointers naming them (inside a transaction)."""
        since = self._live_since()
        db.execute(
            "DELETE FROM live_sessions "
            "WHERE session_id IN (SELECT session_id FROM sessions WHERE updated_at < ?)",
            (since,),
        )
        return db.execute("DELETE FROM sessions WHERE updated_at < ?", (since,)).rowcount

    # sessions -------------------------------------------------------------------------------
    async def create(
        self, record: SessionRecord, max_sessions: int, *, vehicle_key_hash: str | None = None
    ) -> str | None:
        def body(db: sqlite3.Connection) -> str | None:
            vehicle = record.vehicle_id
            if vehicle_key_hash is not None:
                row = db.execute("SELECT key_hash FROM vehicles WHERE vehicle_id = ?", (vehicle,)).fetchone()
                if row is None or row[0] != vehicle_key_hash:
                    raise VehicleNotRegistered(vehicle)
            self._purge_expired(db)
            if db.execute("SELECT 1 FROM sessions WHERE session_id = ?", (record.session_id,)).fetchone():
                raise ValueError(f"session {record.session_id!r} already exists")
            old = db.execute(
                "SELECT s.session_id, s.token_hash FROM live_sessions AS l "
                "JOIN sessions AS s ON s.session_id = l.session_id WHERE l.vehicle_id = ?",
                (vehicle,),
            ).fetchone()
            (count,) = db.execute("SELECT COUNT(*) FROM sessions").fetchone()
            if count - (old is not None) >= max_sessions:  # the superseded one makes room for its successor
                raise TooManySessions(max_sessions)
            superseded = None
            if old is not None:
                superseded, old_token_hash = old
                now = self.clock()
                db.execute("DELETE FROM sessions WHERE session_id = ?", (superseded,))
                db.execute("DELETE FROM supersessions WHERE at < ?", (now - self.ttl_s,))
                db.execute(
                    "INSERT OR REPLACE INTO supersessions (session_id, superseded_by, token_hash, at) "
                    "VALUES (?, ?, ?, ?)",
                    (superseded, record.session_id, old_token_hash, now),
                )
            db.execute("DELETE FROM tracks WHERE vehicle_id = ?", (vehicle,))
            db.execute(
                "INSERT OR REPLACE INTO live_sessions (vehicle_id, session_id) VALUES (?, ?)",
                (vehicle, record.session_id),
            )
            db.execute(
                f"INSERT INTO sessions ({_SESSION_COLUMNS}) VALUES ({', '.join('?' * 15)})",
                self._row(record),
            )
            return superseded

        return await self._run(lambda db: self._transaction(db, lambda: body(db)))

    async def live_session(self, vehicle_id: str) -> str | None:
        def work(db: sqlite3.Connection) -> str | None:
            row = db.execute(_LIVE_SESSION, (vehicle_id, self._live_since())).fetchone()
            return None if row is None else str(row[0])

        return await self._run(work)

    async def supersession(self, session_id: str) -> Supersession | None:
        def work(db: sqlite3.Connection) -> Supersession | None:
            row = db.execute(
                "SELECT session_id, superseded_by, token_hash, at FROM supersessions "
                "WHERE session_id = ? AND at >= ?",
                (session_id, self._live_since()),
            ).fetchone()
            return None if row is None else Supersession(*row)

        return await self._run(work)

    async def list_sessions(
        self,
        *,
        after: str | None = None,
        limit: int = 100,
        pipeline: str | None = None,
        vehicle_id: str | None = None,
    ) -> list[SessionSummary]:
        conditions: list[str] = ["updated_at >= ?"]
        params: list[float | str] = [self._live_since()]
        filters = (("session_id > ?", after), ("pipeline = ?", pipeline), ("vehicle_id = ?", vehicle_id))
        for condition, value in filters:
            if value is not None:
                conditions.append(condition)
                params.append(value)

        def work(db: sqlite3.Connection) -> list[SessionSummary]:
            rows = db.execute(
                f"SELECT {_SUMMARY_COLUMNS} FROM sessions WHERE {' AND '.join(conditions)} "
                "ORDER BY session_id LIMIT ?",
                (*params, max(0, int(limit))),
            ).fetchall()
            return [SessionSummary(*row) for row in rows]

        return await self._run(work)

    async def get(self, session_id: str, *, with_response: bool = True) -> SessionRecord | None:
        def work(db: sqlite3.Connection) -> SessionRecord | None:
            row = db.execute(
                f"SELECT {_SESSION_COLUMNS} FROM sessions WHERE session_id = ? AND updated_at >= ?",
                (session_id, self._live_since()),
            ).fetchone()
            return None if row is None else self._record(row)

        return await self._run(work)

    async def compare_and_set(
        self, record: SessionRecord, expected_version: int, fixes: Sequence[NewFix] = ()
    ) -> bool:
        refuse_fixes_in_write(fixes)

        def work(db: sqlite3.Connection) -> bool:
            row = self._row(record)
            cursor = db.execute(
                "UPDATE sessions SET vehicle_id = ?, pipeline = ?, options = ?, token_hash = ?, "
                "state = ?, created_at = ?, updated_at = ?, last_seq = ?, last_request_hash = ?, "
                "last_response = ?, batches = ?, epochs = ?, last_fix = ?, version = ? "
                "WHERE session_id = ? AND version = ?",
                (*row[1:14], expected_version + 1, record.session_id, expected_version),
            )
            return cursor.rowcount == 1

        return await self._run(work)

    async def delete(self, session_id: str) -> bool:
        def body(db: sqlite3.Connection) -> bool:
            row = db.execute("SELECT vehicle_id FROM sessions WHERE session_id = ?", (session_id,)).fetchone()
            if row is None:
                return False
            db.execute("DELETE FROM sessions WHERE session_id = ?", (session_id,))
            pointer = db.execute(
                "DELETE FROM live_sessions WHERE vehicle_id = ? AND session_id = ?", (row[0], session_id)
            )
            if pointer.rowcount == 1:  # it was the vehicle's live session: its track goes with it
                db.execute("DELETE FROM tracks WHERE vehicle_id = ?", (row[0],))
            return True

        return await self._run(lambda db: self._transaction(db, lambda: body(db)))

    async def count(self) -> int:
        def work(db: sqlite3.Connection) -> int:
            (count,) = db.execute(
                "SELECT COUNT(*) FROM sessions WHERE updated_at >= ?", (self._live_since(),)
            ).fetchone()
            return int(count)

        return await self._run(work)

    async def expire(self) -> int:
        def body(db: sqlite3.Connection) -> int:
            now = self.clock()
            db.execute("DELETE FROM rate_limits WHERE tat < ?", (now,))  # budgets full again
            db.execute("DELETE FROM supersessions WHERE at < ?", (now - self.ttl_s,))
            return self._purge_expired(db)

        return await self._run(lambda db: self._transaction(db, lambda: body(db)))

    # vehicle registry -----------------------------------------------------------------------
    @staticmethod
    def _vehicle(row: tuple[Any, ...]) -> VehicleRecord:
        vehicle_id, key_hash, created_at, key_issued_at = row
        return VehicleRecord(vehicle_id, key_hash, float(created_at), float(key_issued_at))

    async def add_vehicles(self, vehicles: Sequence[VehicleRecord]) -> list[str]:
        rows = [(v.vehicle_id, v.key_hash, float(v.created_at), float(v.key_issued_at)) for v in vehicles]

        def body(db: sqlite3.Connection) -> list[str]:
            added = []
            for row in rows:
                cursor = db.execute(
                    f"INSERT INTO vehicles ({_VEHICLE_COLUMNS}) VALUES (?, ?, ?, ?) "
                    "ON CONFLICT (vehicle_id) DO NOTHING",
                    row,
                )
                if cursor.rowcount == 1:
                    added.append(row[0])
            return added

        try:
            return await self._run(lambda db: self._transaction(db, lambda: body(db)))
        except sqlite3.IntegrityError as error:  # key_hash UNIQUE: one key never opens two vehicles
            raise ValueError("a vehicle key hash is already another vehicle's; nothing was added") from error

    async def get_vehicle(self, vehicle_id: str) -> VehicleRecord | None:
        def work(db: sqlite3.Connection) -> VehicleRecord | None:
            row = db.execute(
                f"SELECT {_VEHICLE_COLUMNS} FROM vehicles WHERE vehicle_id = ?", (vehicle_id,)
            ).fetchone()
            return None if row is None else self._vehicle(row)

        return await self._run(work)

    async def vehicle_of_key(self, key_hash: str) -> str | None:
        def work(db: sqlite3.Connection) -> str | None:
            row = db.execute("SELECT vehicle_id FROM vehicles WHERE key_hash = ?", (key_hash,)).fetchone()
            return None if row is None else str(row[0])

        return await self._run(work)

    async def list_vehicles(self, *, after: str | None = None, limit: int = 100) -> list[VehicleRecord]:
        def work(db: sqlite3.Connection) -> list[VehicleRecord]:
            rows = db.execute(
                f"SELECT {_VEHICLE_COLUMNS} FROM vehicles WHERE ? IS NULL OR vehicle_id > ? "
                "ORDER BY vehicle_id LIMIT ?",
                (after, after, max(0, int(limit))),
            ).fetchall()
            return [self._vehicle(row) for row in rows]

        return await self._run(work)

    async def count_vehicles(self) -> int:
        def work(db: sqlite3.Connection) -> int:
            (count,) = db.execute("SELECT COUNT(*) FROM vehicles").fetchone()
            return int(count)

        return await self._run(work)

    async def rotate_vehicle_key(self, vehicle_id: str, key_hash: str, now: float) -> VehicleRecord | None:
        def body(db: sqlite3.Connection) -> VehicleRecord | None:
            cursor = db.execute(
                "UPDATE vehicles SET key_hash = ?, key_issued_at = ? WHERE vehicle_id = ?",
                (key_hash, float(now), vehicle_id),
            )
            if cursor.rowcount == 0:
                return None
            row = db.execute(
                f"SELECT {_VEHICLE_COLUMNS} FROM vehicles WHERE vehicle_id = ?", (vehicle_id,)
            ).fetchone()
            return self._vehicle(row)

        try:
            return await self._run(lambda db: self._transaction(db, lambda: body(db)))
        except sqlite3.IntegrityError as error:
            raise ValueError("the new key hash is already another vehicle's; nothing was changed") from error

    async def delete_vehicle(self, vehicle_id: str) -> Revocation | None:
        def body(db: sqlite3.Connection) -> Revocation | None:
            if db.execute("DELETE FROM vehicles WHERE vehicle_id = ?", (vehicle_id,)).rowcount == 0:
                return None
            live = db.execute(_LIVE_SESSION, (vehicle_id, self._live_since())).fetchone()
            pointer = db.execute(
                "SELECT session_id FROM live_sessions WHERE vehicle_id = ?", (vehicle_id,)
            ).fetchone()
            if pointer is not None:
                db.execute("DELETE FROM sessions WHERE session_id = ?", (pointer[0],))
                db.execute("DELETE FROM live_sessions WHERE vehicle_id = ?", (vehicle_id,))
            db.execute("DELETE FROM tracks WHERE vehicle_id = ?", (vehicle_id,))
            return Revocation(vehicle_id, None if live is None else str(live[0]))

        return await self._run(lambda db: self._transaction(db, lambda: body(db)))

    # RSUs -----------------------------------------------------------------------------------
    async def upsert_rsus(self, rsus: Iterable[Rsu]) -> int:
        rows = [(r.id, r.x, r.y, r.range_std, r.bearing_std, r.radius) for r in rsus]

        def work(db: sqlite3.Connection) -> int:
            db.execute("BEGIN IMMEDIATE")
            try:
                db.executemany("INSERT OR REPLACE INTO rsus VALUES (?, ?, ?, ?, ?, ?)", rows)
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")
            return len(rows)

        return await self._run(work)

    async def get_rsu(self, rsu_id: str) -> Rsu | None:
        found = await self.get_rsus([rsu_id])
        return found.get(rsu_id)

    async def get_rsus(self, rsu_ids: Iterable[str]) -> Mapping[str, Rsu]:
        wanted = sorted(set(rsu_ids))

        def work(db: sqlite3.Connection) -> Mapping[str, Rsu]:
            found: dict[str, Rsu] = {}
            for start in range(0, len(wanted), 500):
                chunk = wanted[start : start + 500]
                rows = db.execute(
                    f"SELECT id, x, y, range_std, bearing_std, radius FROM rsus "
                    f"WHERE id IN ({', '.join('?' * len(chunk))})",
                    chunk,
                ).fetchall()
                found.update({row[0]: Rsu(*row) for row in rows})
            return found

        return await self._run(work)

    async def list_rsus(self) -> list[Rsu]:
        def work(db: sqlite3.Connection) -> list[Rsu]:
            rows = db.execute("SELECT id, x, y, range_std, bearing_std, radius FROM rsus ORDER BY id")
            return [Rsu(*row) for row in rows.fetchall()]

        return await self._run(work)

    async def delete_rsu(self, rsu_id: str) -> bool:
        def work(db: sqlite3.Connection) -> bool:
            return db.execute("DELETE FROM rsus WHERE id = ?", (rsu_id,)).rowcount == 1

        return await self._run(work)

    # broadcast ephemerides ------------------------------------------------------------------
    async def put_ephemerides(self, document: StoredEphemerides) -> None:
        def work(db: sqlite3.Connection) -> None:
            db.execute(
                "INSERT OR REPLACE INTO ephemerides VALUES (0, ?, ?, ?)",
                (document.digest, document.text, document.uploaded_at),
            )

        await self._run(work)

    async def get_ephemerides(self) -> StoredEphemerides | None:
        def work(db: sqlite3.Connection) -> StoredEphemerides | None:
            row = db.execute("SELECT digest, text, uploaded_at FROM ephemerides WHERE slot = 0").fetchone()
            return None if row is None else StoredEphemerides(*row)

        return await self._run(work)

    async def ephemerides_digest(self) -> str | None:
        def work(db: sqlite3.Connection) -> str | None:
            row = db.execute("SELECT digest FROM ephemerides WHERE slot = 0").fetchone()
            return None if row is None else str(row[0])

        return await self._run(work)

    async def delete_ephemerides(self) -> bool:
        def work(db: sqlite3.Connection) -> bool:
            return db.execute("DELETE FROM ephemerides WHERE slot = 0").rowcount == 1

        return await self._run(work)

    # neighbour tracks (one row per vehicle, replaced whole) ---------------------------------
    async def put_track(self, track: NeighbourTrack, session_id: str) -> bool:
        now = self.clock()
        vehicle = track.vehicle_id

        def work(db: sqlite3.Connection) -> bool:
            # One statement, so the check and the write are atomic (autocommit mode).
            cursor = db.execute(
                "INSERT OR REPLACE INTO tracks (vehicle_id, written_at, track) "
                f"SELECT ?, ?, ? WHERE EXISTS ({_LIVE_SESSION} AND l.session_id = ?)",
                (vehicle, now, encode_track(track, now), vehicle, now - self.ttl_s, session_id),
            )
            return cursor.rowcount == 1

        return await self._run(work)

    async def get_tracks(self, vehicle_ids: Iterable[str]) -> Mapping[str, NeighbourTrack]:
        wanted = sorted(set(vehicle_ids))
        since = self._live_since()

        def work(db: sqlite3.Connection) -> Mapping[str, NeighbourTrack]:
            found: dict[str, NeighbourTrack] = {}
            for start in range(0, len(wanted), 500):
                chunk = wanted[start : start + 500]
                rows = db.execute(
                    f"SELECT vehicle_id, track FROM tracks "
                    f"WHERE written_at >= ? AND vehicle_id IN ({', '.join('?' * len(chunk))})",
                    (since, *chunk),
                ).fetchall()
                found.update({vehicle: decode_track(vehicle, text)[0] for vehicle, text in rows})
            return found

        return await self._run(work)

    async def delete_track(self, vehicle_id: str) -> bool:
        def work(db: sqlite3.Connection) -> bool:
            return db.execute("DELETE FROM tracks WHERE vehicle_id = ?", (vehicle_id,)).rowcount == 1

        return await self._run(work)

    # request-rate limits --------------------------------------------------------------------
    async def take_request(self, key: str, limit: RateLimit) -> float:
        def work(db: sqlite3.Connection) -> float:
            db.execute("BEGIN IMMEDIATE")
            try:
                row = db.execute("SELECT tat FROM rate_limits WHERE key = ?", (key,)).fetchone()
                wait, tat = gcra(None if row is None else row[0], self.clock(), limit)
                if tat is not None:
                    db.execute("INSERT OR REPLACE INTO rate_limits VALUES (?, ?)", (key, tat))
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")
            return wait

        return await self._run(work)

    async def request_wait(self, key: str, limit: RateLimit) -> float:
        def work(db: sqlite3.Connection) -> float:
            row = db.execute("SELECT tat FROM rate_limits WHERE key = ?", (key,)).fetchone()
            return gcra(None if row is None else row[0], self.clock(), limit)[0]

        return await self._run(work)

    async def close(self) -> None:
        """Close the connection and stop the thread; a later call reopens both."""
        await self._database.close()
