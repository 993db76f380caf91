"""The store interface: where sessions (the core's serialised state plus bookkeeping), the site's
RSU registry and its broadcast ephemerides live.

The web layer only talks to :class:`SessionStore`, so the same routes run on the in-process store
(one worker) and on the SQLite store (several workers on one box); a shared network store can come
later without touching the routes. Records are immutable values: an update is a compare-and-set on
``version``, so two writers can never both apply a batch to the same state.
"""

from __future__ import annotations

import asyncio
import json
import time
from abc import ABC, abstractmethod
from collections.abc import AsyncIterator, Callable, Iterable, Mapping
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any

from edgepos.pipelines.base import NeighbourTrack, Rsu, TrackPoint
from edgepos.store.ratelimit import RateLimit

Clock = Callable[[], float]


@dataclass(frozen=True)
class SessionRecord:
    """Everything the service keeps about one vehicle session.

    ``state`` is the pipeline's opaque state; ``token_hash`` the SHA-256 hex of the session token
    (the token itself is never stored); ``last_request_hash`` / ``last_response`` let a retried last
    batch be answered verbatim; ``version`` increases by one on every successful write.
    """

    session_id: str
    vehicle_id: str
    pipeline: str
    options: dict[str, Any]
    token_hash: str
    state: bytes
    created_at: float
    updated_at: float
    last_seq: int = 0
    last_request_hash: str | None = None
    last_response: bytes | None = None
    batches: int = 0
    epochs: int = 0
    last_fix: str | None = None
    version: int = 0


@dataclass(frozen=True)
class StoredEphemerides:
    """The site's broadcast navigation file as uploaded (``PUT /v1/ephemerides``).

    ``text`` is the RINEX navigation text exactly as received; ``digest`` its SHA-256 hex, by which
    every worker caches the parsed form; ``uploaded_at`` Unix seconds (server clock)."""

    digest: str
    text: str
    uploaded_at: float


def encode_track(track: NeighbourTrack, written_at: float) -> str:
    """One track as one JSON text (floats round-trip exactly): stores keep it as a single value, so a
    reader sees either the whole previous track or the whole new one."""
    points = [[p.t, p.x, p.y, p.vx, p.vy, [list(row) for row in p.cov]] for p in track.points]
    return json.dumps({"written_at": written_at, "points": points}, allow_nan=False)


def decode_track(vehicle_id: str, text: str | bytes) -> tuple[NeighbourTrack, float]:
    """The track and the server time it was written (inverse of :func:`encode_track`)."""
    value = json.loads(text)
    points = tuple(
        TrackPoint(t, x, y, vx, vy, tuple(tuple(row) for row in cov)) for t, x, y, vx, vy, cov in value["points"]
    )
    return NeighbourTrack(vehicle_id, points), float(value["written_at"])


class TooManySessions(Exception):
    """The store already holds ``limit`` live sessions."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        super().__init__(f"the store already holds {limit} sessions")


class StoreUnavailable(Exception):
    """The store did not answer in time or refused service (down, unreachable, loading, read-only).
    A write may or may not have been applied; retrying is safe (updates are compare-and-set)."""


class SessionLocks:
    """One asyncio lock per session id, dropped when nobody holds or awaits it.

    This serialises requests for the same session inside one process; across processes the
    stores' compare-and-set on ``version`` keeps updates from being lost.
    """

    def __init__(self) -> None:
        self._locks: dict[str, tuple[asyncio.Lock, int]] = {}

    @asynccontextmanager
    async def hold(self, session_id: str) -> AsyncIterator[None]:
        lock, users = self._locks.get(session_id, (None, 0))
        if lock is None:
            lock = asyncio.Lock()
        self._locks[session_id] = (lock, users + 1)
        try:
            async with lock:
                yield
        finally:
            lock, users = self._locks[session_id]
            if users <= 1:
                del self._locks[session_id]
            else:
                self._locks[session_id] = (lock, users - 1)

    def __len__(self) -> int:
        return len(self._locks)


class SessionStore(ABC):
    """Async storage of sessions and RSUs. Sessions idle for more than ``ttl_s`` seconds (no write
    since ``updated_at``) are expired: never returned, not counted, removed by :meth:`expire`."""

    def __init__(self, ttl_s: float, clock: Clock = time.time) -> None:
        if not ttl_s > 0:
            raise ValueError("ttl_s must be > 0")
        self.ttl_s = float(ttl_s)
        self.clock = clock
        self.locks = SessionLocks()

    def is_expired(self, record: SessionRecord, now: float) -> bool:
        return now - record.updated_at > self.ttl_s

    def session_lock(self, session_id: str) -> Any:
        """Async context manager: hold it around load -> process -> compare-and-set."""
        return self.locks.hold(session_id)

    # sessions
    @abstractmethod
    async def create(self, record: SessionRecord, max_sessions: int) -> None:
        """Insert a new session unless ``max_sessions`` live ones exist (raises TooManySessions)."""

    @abstractmethod
    async def get(self, session_id: str) -> SessionRecord | None:
        """The live session, or None if unknown or expired."""

    @abstractmethod
    async def compare_and_set(self, record: SessionRecord, expected_version: int) -> bool:
        """Replace the session if its stored version is still ``expected_version``; the stored
        copy gets version ``expected_version + 1``. False if it changed or vanished meanwhile."""

    @abstractmethod
    async def delete(self, session_id: str) -> bool:
        """Remove a session; False if there was none."""

    @abstractmethod
    async def count(self) -> int:
        """How many live (unexpired) sessions there are."""

    @abstractmethod
    async def expire(self) -> int:
        """Remove every session idle past the TTL; returns how many went."""

    # RSU registry
    @abstractmethod
    async def upsert_rsus(self, rsus: Iterable[Rsu]) -> int:
        """Insert or replace RSUs by id; returns how many were written."""

    @abstractmethod
    async def get_rsu(self, rsu_id: str) -> Rsu | None: ...

    @abstractmethod
    async def get_rsus(self, rsu_ids: Iterable[str]) -> Mapping[str, Rsu]:
        """The known RSUs among ``rsu_ids`` (unknown ones are simply absent)."""

    @abstractmethod
    async def list_rsus(self) -> list[Rsu]:
        """Every RSU, sorted by id."""

    @abstractmethod
    async def delete_rsu(self, rsu_id: str) -> bool: ...

    # broadcast ephemerides (one navigation file per site, shared like the RSU registry)
    @abstractmethod
    async def put_ephemerides(self, document: StoredEphemerides) -> None:
        """Store the site's navigation file, replacing any previous one (one atomic write)."""

    @abstractmethod
    async def get_ephemerides(self) -> StoredEphemerides | None:
        """The stored navigation file (digest, text and time read together), None when none is."""

    @abstractmethod
    async def ephemerides_digest(self) -> str | None:
        """Only the stored file's digest: a cheap check of whether a worker's parsed copy is current."""

    @abstractmethod
    async def delete_ephemerides(self) -> bool:
        """Remove the navigation file; False if there was none."""

    # neighbour tracks: what a vehicle's session publishes for cooperative pipelines of other vehicles
    def track_is_live(self, written_at: float, now: float) -> bool:
        """A track lives as long as an idle session would (``ttl_s`` since it was written)."""
        return now - written_at <= self.ttl_s

    @abstractmethod
    async def put_track(self, track: NeighbourTrack) -> None:
        """Replace the track published under ``track.vehicle_id``, as one atomic value."""

    @abstractmethod
    async def get_tracks(self, vehicle_ids: Iterable[str]) -> Mapping[str, NeighbourTrack]:
        """The live tracks among ``vehicle_ids`` (unknown or expired ones are absent)."""

    @abstractmethod
    async def delete_track(self, vehicle_id: str) -> bool:
        """Remove a vehicle's track; False if there was none."""

    # request-rate limits
    @abstractmethod
    async def take_request(self, key: str, limit: RateLimit) -> float:
        """Count one request against ``key``'s budget (see edgepos.store.ratelimit): 0.0 when it is
        allowed, else the seconds until it would be (a refused request uses no budget). Shared by
        every process that shares the store, so the limit holds across workers."""

    # lifecycle
    async def ping(self) -> bool:
        """True when the store answers (used by /readyz)."""
        await self.count()
        return True

    async def close(self) -> None:
        """Release connections and threads (nothing to release by default)."""
        return None
