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
import secrets
import time
from abc import ABC, abstractmethod
from collections.abc import AsyncIterator, Callable, Iterable, Mapping, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any

from edgepos.pipelines.base import NeighbourTrack, Rsu, TrackPoint
from edgepos.store.fixlog import FixLog, MemoryFixLog, NewFix
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
class SessionSummary:
    """What an operator's listing shows of a session (``GET /v1/sessions``): no state, no secrets."""

    session_id: str
    vehicle_id: str
    pipeline: str
    created_at: float
    updated_at: float
    last_seq: int
    batches: int
    epochs: int
    last_fix: str | None

    @classmethod
    def of(cls, record: SessionRecord) -> SessionSummary:
        return cls(
            record.session_id,
            record.vehicle_id,
            record.pipeline,
            record.created_at,
            record.updated_at,
            record.last_seq,
            record.batches,
            record.epochs,
            record.last_fix,
        )


@dataclass(frozen=True)
class Supersession:
    """A session ended because a newer one was opened for its vehicle (one live session per vehicle).

    Kept as long as an idle session would be, so the old token is told which session replaced it
    (409) instead of being answered as if it never existed; ``token_hash`` is the old session's, so
    only its holder learns that."""

    session_id: str
    superseded_by: str
    token_hash: str
    at: float


@dataclass(frozen=True)
class VehicleRecord:
    """A registered vehicle: who may open sessions for ``vehicle_id`` with a vehicle key.

    ``key_hash`` is the SHA-256 hex of the vehicle's current key (the key itself is shown once, when
    it is issued, and never stored); ``key_issued_at`` when that key was issued (Unix s)."""

    vehicle_id: str
    key_hash: str
    created_at: float
    key_issued_at: float


@dataclass(frozen=True)
class Revocation:
    """What revoking a vehicle ended: ``ended_session`` is its live session's id, None if it had none."""

    vehicle_id: str
    ended_session: str | None


@dataclass(frozen=True)
class StoredEphemerides:
    """The site's broadcast navigation file as uploaded (``PUT /v1/ephemerides``).

    ``text`` is the RINEX navigation text exactly as received; ``digest`` its SHA-256 hex, by which
    every worker caches the parsed form; ``uploaded_at`` Unix seconds (server clock)."""

    digest: str
    text: str
    uploaded_at: float


@dataclass(frozen=True)
class StoredBaseStation:
    """A registered reference station (``POST /v1/base-stations``): ``document`` is its registration as the
    web layer encodes it (JSON: position, antenna delta, where the position came from); ``updated_at`` Unix
    seconds of the last change of the document."""

    station_id: str
    document: str
    updated_at: float


@dataclass(frozen=True)
class BaseWindow:
    """A station and the part of its correction window a batch needs: the epochs (GPS s, document) with
    ``since <= gpst <= until`` in time order, preceded by the newest epoch before ``since`` if there is one
    (so a rover can be told that the newest correction is too old rather than that there is none)."""

    station: StoredBaseStation
    epochs: tuple[tuple[float, str], ...]


def encode_track(track: NeighbourTrack, written_at: float) -> str:
    """One track as one JSON text (floats round-trip exactly): stores keep it as a single value, so a
    reader sees either the whole previous track or the whole new one."""
    points = [[p.t, p.x, p.y, p.vx, p.vy, [list(row) for row in p.cov]] for p in track.points]
    return json.dumps({"written_at": written_at, "points": points}, allow_nan=False)


def decode_track(vehicle_id: str, text: str | bytes) -> tuple[NeighbourTrack, float]:
    """The track and the server time it was written (inverse of :func:`encode_track`)."""
    value = json.loads(text)
    points = tuple(
        TrackPoint(t, x, y, vx, vy, tuple(tuple(row) for row in cov))
        for t, x, y, vx, vy, cov in value["points"]
    )
    return NeighbourTrack(vehicle_id, points), float(value["written_at"])


class TooManySessions(Exception):
    """The store already holds ``limit`` live sessions."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        super().__init__(f"the store already holds {limit} sessions")


class VehicleNotRegistered(Exception):
    """The vehicle is not registered, or its key is no longer the one given (revoked or rotated)."""

    def __init__(self, vehicle_id: str) -> None:
        self.vehicle_id = vehicle_id
        super().__init__(f"vehicle {vehicle_id!r} is not registered with this key")


class StoreUnavailable(Exception):
    """The store did not answer in time or refused service (down, unreachable, loading, read-only).
    A write may or may not have been applied; retrying is safe (updates are compare-and-set)."""


class NotReplicated(StoreUnavailable):
    """The write is on the primary but not on as many replicas as configured in time: not acknowledged.
    Its message names no host or port and is shown to the client."""


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

    def busy(self, session_id: str) -> bool:
        """Whether a request of this process holds or awaits the session's lock right now."""
        return session_id in self._locks

    def __len__(self) -> int:
        return len(self._locks)


def refuse_fixes_in_write(fixes: Sequence[NewFix]) -> None:
    """For a store whose compare-and-set cannot append fix events (``SessionStore.fixes_in_write``)."""
    if fixes:
        raise ValueError("this store appends fix events to its fix log apart from the session's write")


class SessionStore(ABC):
    """Async storage of sessions and RSUs. Sessions idle for more than ``ttl_s`` seconds (no write
    since ``updated_at``) are expired: never returned, not counted, removed by :meth:`expire`."""

    fixes_in_write = False
    """Whether :meth:`compare_and_set` takes the batch's fix events and appends them to the store's fix log in
    the same atomic write (the Redis store, once its fix log is made); else they go to the log apart."""

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
    async def create(
        self, record: SessionRecord, max_sessions: int, *, vehicle_key_hash: str | None = None
    ) -> str | None:
        """Insert a new session as its vehicle's one live session, in one atomic step.

        A live session the vehicle already has is superseded: removed, remembered as a
        :class:`Supersession` for ``ttl_s``, and its published track deleted. Returns the superseded
        session's id (None when there was none). Raises TooManySessions when ``max_sessions`` live
        sessions exist (a superseded one does not count) and, with ``vehicle_key_hash``,
        VehicleNotRegistered unless the vehicle is registered with exactly that key at this moment
        (a key revoked or rotated while the request was on its way opens nothing)."""

    @abstractmethod
    async def live_session(self, vehicle_id: str) -> str | None:
        """The id of the vehicle's live session, None when it has none."""

    @abstractmethod
    async def supersession(self, session_id: str) -> Supersession | None:
        """How ``session_id`` was superseded, if it was (within ``ttl_s``)."""

    @abstractmethod
    async def list_sessions(
        self,
        *,
        after: str | None = None,
        limit: int = 100,
        pipeline: str | None = None,
        vehicle_id: str | None = None,
    ) -> list[SessionSummary]:
        """Live sessions ordered by session id, those with ids greater than ``after``, at most
        ``limit``, optionally only of one pipeline and/or one vehicle."""

    @abstractmethod
    async def get(self, session_id: str, *, with_response: bool = True) -> SessionRecord | None:
        """The live session, or None if unknown or expired. ``with_response=False`` lets the store leave
        the stored answer of the last batch out (``last_response`` None): for readers that only check the
        token or apply the next seq, which never replay it (the Redis store then reads 30 kB less per
        20-epoch batch)."""

    async def get_for_batch(self, session_id: str) -> SessionRecord | None:
        """The record a batch's token check reads and the batch applies its next seq on (its stored answer
        may be left out). A store may answer from the record it last wrote for the session without asking
        its server: the batch's compare-and-set on the record's version then refuses one that went stale
        (another worker wrote; the session was deleted, superseded, revoked or expired), and the batch is
        redone on a fresh read. Default: ``get(with_response=False)``."""
        return await self.get(session_id, with_response=False)

    @abstractmethod
    async def compare_and_set(
        self, record: SessionRecord, expected_version: int, fixes: Sequence[NewFix] = ()
    ) -> bool:
        """Replace the session if its stored version is still ``expected_version``; the stored
        copy gets version ``expected_version + 1``. False if it changed or vanished meanwhile.
        ``fixes``: the batch's fix events, appended with the write if and only if it applies; only for a
        store whose :attr:`fixes_in_write` (ValueError otherwise)."""

    @abstractmethod
    async def delete(self, session_id: str) -> bool:
        """Remove a session, and with it its vehicle's live-session entry and published track when
        they are this session's; False if there was none."""

    @abstractmethod
    async def count(self) -> int:
        """How many live (unexpired) sessions there are."""

    @abstractmethod
    async def expire(self) -> int:
        """Remove every session idle past the TTL; returns how many went."""

    # vehicle registry
    @abstractmethod
    async def add_vehicles(self, vehicles: Sequence[VehicleRecord]) -> list[str]:
        """Register the vehicles not registered yet (one atomic write); returns the ids added, in the
        order given. Registered ones are left as they are (their keys are not replaced)."""

    @abstractmethod
    async def get_vehicle(self, vehicle_id: str) -> VehicleRecord | None: ...

    @abstractmethod
    async def vehicle_of_key(self, key_hash: str) -> str | None:
        """The vehicle whose current key has this hash, None when no vehicle's has."""

    @abstractmethod
    async def list_vehicles(self, *, after: str | None = None, limit: int = 100) -> list[VehicleRecord]:
        """Registered vehicles ordered by id, those with ids greater than ``after``, at most ``limit``."""

    @abstractmethod
    async def count_vehicles(self) -> int: ...

    @abstractmethod
    async def rotate_vehicle_key(self, vehicle_id: str, key_hash: str, now: float) -> VehicleRecord | None:
        """Replace the vehicle's key (the old one opens nothing from now on); None when the vehicle
        is not registered. Live sessions keep running: their own tokens are not the vehicle key."""

    @abstractmethod
    async def delete_vehicle(self, vehicle_id: str) -> Revocation | None:
        """Revoke the vehicle: remove it and its key, end its live session and delete its track, in
        one atomic step. None when it was not registered."""

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

    # reference stations and their corrections (shared like the ephemerides)
    @abstractmethod
    async def add_base_station(self, station: StoredBaseStation) -> bool:
        """Register a station; False (nothing written) when one with its id exists."""

    @abstractmethod
    async def replace_base_station(self, station: StoredBaseStation) -> bool:
        """Replace a registered station's document (its corrections stay); False when it is not registered."""

    @abstractmethod
    async def get_base_station(self, station_id: str) -> StoredBaseStation | None: ...

    @abstractmethod
    async def list_base_stations(self) -> list[StoredBaseStation]:
        """Every registered station, sorted by id."""

    @abstractmethod
    async def delete_base_station(self, station_id: str) -> bool:
        """Remove a station and its corrections; False if it was not registered."""

    @abstractmethod
    async def add_base_epochs(
        self, station_id: str, epochs: Sequence[tuple[float, str]], keep: int
    ) -> int | None:
        """Add correction epochs (GPS s, document) to a station's window, replacing any of the same time,
        then drop the oldest beyond the newest ``keep``, in one atomic step. The window's size after, None
        (nothing written) when the station is not registered."""

    @abstractmethod
    async def base_window(self, station_id: str, since: float, until: float) -> BaseWindow | None:
        """One read: the station and its epochs from ``since`` to ``until`` (see :class:`BaseWindow`); None
        when it is not registered."""

    # neighbour tracks: what a vehicle's session publishes for cooperative pipelines of other vehicles
    def track_is_live(self, written_at: float, now: float) -> bool:
        """A track lives as long as an idle session would (``ttl_s`` since it was written)."""
        return now - written_at <= self.ttl_s

    @abstractmethod
    async def put_track(self, track: NeighbourTrack, session_id: str) -> bool:
        """Replace the track published under ``track.vehicle_id``, as one atomic value, if
        ``session_id`` is still that vehicle's live session (else nothing is written and False is
        returned): a superseded session's late write can never mix into its successor's track."""

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

    @abstractmethod
    async def request_wait(self, key: str, limit: RateLimit) -> float:
        """The seconds until one more request of ``key`` would be allowed (0.0 now), using none of
        its budget: a look before work that must not even start past the limit."""

    # documents of the location adapter (zones, subscriptions): small JSON texts by kind and key
    @abstractmethod
    async def put_document(self, kind: str, key: str, text: str) -> None:
        """Insert or replace the document ``key`` of ``kind`` (one atomic write)."""

    @abstractmethod
    async def replace_document(self, kind: str, key: str, text: str) -> bool:
        """Replace the document only if it still exists (False, writing nothing, when it was deleted):
        a background writer's late update never brings back a document a client deleted."""

    @abstractmethod
    async def get_document(self, kind: str, key: str) -> str | None: ...

    @abstractmethod
    async def list_documents(self, kind: str) -> dict[str, str]:
        """Every document of ``kind``, by key (in key order)."""

    @abstractmethod
    async def delete_document(self, kind: str, key: str) -> bool:
        """Remove the document; False if there was none."""

    @abstractmethod
    async def acquire_lease(self, name: str, owner: str, ttl_s: float) -> bool:
        """Take or renew the lease ``name`` for ``owner`` for ``ttl_s`` seconds: True when ``owner`` holds
        it now (it was free, expired, or already its own), False while another owner's lease runs.
        Every process sharing the store sees the same holder, so one of them does a shared job."""

    def new_session_id(self, vehicle_id: str) -> str:
        """A fresh, unguessable session id (32 hex digits) for a session of ``vehicle_id``. A store that
        shards may put the vehicle's shard in it, so that a session's keys are found without a lookup."""
        return secrets.token_hex(16)

    async def make_durable(self, session_id: str) -> None:
        """Return once what this store has acknowledged so far for ``session_id`` is as durable as it is configured to
        make it (Redis with ``wait_replicas``: on that many replicas), else raise StoreUnavailable. A
        replayed answer is sent only after this, so a retry cannot acknowledge a batch that the first
        attempt stored but could not replicate. Nothing to wait for by default."""
        return

    # the fix stream (GET /v1/stream/fixes)
    def fix_log(self, buffer: int) -> FixLog:
        """A new handle on the log of applied fixes that this store's processes share, holding the last
        ``buffer`` events. By default the log lives in this process, which is right for a store that
        serves one process only (the in-process store); shared stores share it through themselves."""
        return MemoryFixLog(buffer)

    # lifecycle
    async def ping(self) -> bool:
        """True when the store answers (used by /readyz)."""
        await self.count()
        return True

    async def close(self) -> None:
        """Release connections and threads (nothing to release by default)."""
        return
