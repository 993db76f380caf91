"""The default store: dicts in this process. Fast and simple; sessions are lost on restart and not
shared between worker processes (``edgepos serve --workers N`` refuses it for N > 1)."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import time
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from edgepos.pipelines.base import NeighbourTrack, Rsu
from edgepos.store.base import (
    BaseWindow,
    Clock,
    Revocation,
    SessionRecord,
    SessionStore,
    SessionSummary,
    StoredBaseStation,
    StoredEphemerides,
    Supersession,
    TooManySessions,
    VehicleNotRegistered,
    VehicleRecord,
    refuse_fixes_in_write,
)
from edgepos.store.fixlog import FixEvent, FixLog, Gap, LocalFixLog, NewFix, gap_between
from edgepos.store.ratelimit import RateLimit, gcra

#: Past this many rate-limit entries, entries whose budget is full again are dropped.
_RATE_ENTRIES_BEFORE_PRUNING = 4096


_IMMUTABLE = frozenset({str, int, float, bool, type(None)})


def _copy_options(value: Any) -> Any:
    """A deep copy of a session's options (JSON-like: dicts, lists, numbers, strings), made on every read
    and write of a record so that no caller shares the stored dict; a third of ``copy.deepcopy``'s time,
    which pays for its memo on every batch. Anything else is handed to ``copy.deepcopy``. A dict's or
    list's immutable items are kept without a call each (most of an options dict's values are)."""
    kind = type(value)
    if kind is dict:
        return {key: item if type(item) in _IMMUTABLE else _copy_options(item) for key, item in value.items()}
    if kind is list:
        return [item if type(item) in _IMMUTABLE else _copy_options(item) for item in value]
    if kind is tuple:
        return tuple(_copy_options(item) for item in value)
    if kind in _IMMUTABLE:
        return value
    return copy.deepcopy(value)


class AppendedFixLog(LocalFixLog):
    """The in-process store's fix log: :class:`~edgepos.store.fixlog.MemoryFixLog`'s events, each held as
    the fix that was appended and made a :class:`FixEvent` only when it is read (its id follows from its
    place, the ids being dense). Every applied batch appends its fixes, and most of the time no consumer
    reads them: an event object per fix, made on the event loop as the fix is appended, cost about
    half a microsecond each, about a hundredth of a batch request's Python."""

    def __init__(self, buffer: int) -> None:
        super().__init__(buffer)
        self._fixes: deque[NewFix] = deque(maxlen=self.buffer)

    def append_now(self, fixes: Sequence[NewFix]) -> bool:
        """:meth:`append`, done at once: the log is this process's memory, so appending never waits."""
        self._fixes.extend(fixes)
        self._newest += len(fixes)
        if fixes:
            self._appended_now()
        return True

    async def append(self, fixes: Sequence[NewFix]) -> None:
        self.append_now(fixes)

    def _after(self, after: int, count: int) -> list[FixEvent]:
        fixes = self._fixes
        if not fixes or after >= self._newest:
            return []
        oldest = self._newest - len(fixes) + 1
        start = max(0, after + 1 - oldest)
        return [
            FixEvent(oldest + start + n, fix.session_id, fix.vehicle_id, fix.pipeline, fix.t, fix.data)
            for n, fix in enumerate(itertools.islice(fixes, start, start + count))
        ]

    async def backlog(self, after: int) -> tuple[list[FixEvent], Gap | None]:
        oldest = self._newest - len(self._fixes) + 1 if self._fixes else None
        gap = gap_between(after, oldest, self._newest)
        return self._after(-1 if gap is not None else after, self.buffer), gap


class MemoryStore(SessionStore):
    """Sessions and RSUs in dicts. Every method runs on the event loop without awaiting, so each
    is atomic with respect to other requests of this process."""

    def __init__(self, ttl_s: float, clock: Clock = time.time) -> None:
        super().__init__(ttl_s, clock)
        self._sessions: dict[str, SessionRecord] = {}
        self._rsus: dict[str, Rsu] = {}
        self._tracks: dict[str, tuple[NeighbourTrack, float]] = {}
        self._rate_tats: dict[str, float] = {}
        self._ephemerides: StoredEphemerides | None = None
        self._base_stations: dict[str, StoredBaseStation] = {}
        self._base_epochs: dict[str, dict[float, str]] = {}  # station id -> GPS s -> document
        self._live: dict[str, str] = {}  # vehicle id -> its live session's id
        self._superseded: dict[str, Supersession] = {}
        self._vehicles: dict[str, VehicleRecord] = {}
        self._vehicle_of_key: dict[str, str] = {}  # key hash -> vehicle id
        self._documents: dict[str, dict[str, str]] = {}  # kind -> key -> text
        self._leases: dict[str, tuple[str, float]] = {}  # name -> (owner, expires at)

    @staticmethod
    def _copy(record: SessionRecord, version: int | None = None) -> SessionRecord:
        """The record with its own copy of the options (and ``version`` when given). Built as a copy of
        the frozen record's ``__dict__``, which is what ``dataclasses.replace`` gives a dataclass without
        ``__post_init__`` or init-less fields (a test holds SessionRecord to that), at a tenth of its
        cost: its ``__init__`` sets the fifteen fields one ``object.__setattr__`` at a time, and a batch
        copies a record twice here."""
        copied = object.__new__(SessionRecord)
        fields = copied.__dict__
        fields.update(record.__dict__)
        fields["options"] = _copy_options(record.options)
        if version is not None:
            fields["version"] = version
        return copied

    async def create(
        self, record: SessionRecord, max_sessions: int, *, vehicle_key_hash: str | None = None
    ) -> str | None:
        if record.session_id in self._sessions:
            raise ValueError(f"session {record.session_id!r} already exists")
        if vehicle_key_hash is not None:
            vehicle = self._vehicles.get(record.vehicle_id)
            if vehicle is None or vehicle.key_hash != vehicle_key_hash:
                raise VehicleNotRegistered(record.vehicle_id)
        old_id = self._live.get(record.vehicle_id)
        old = self._sessions.get(old_id) if old_id is not None else None
        if old is not None and self.is_expired(old, self.clock()):
            del self._sessions[old.session_id]
            old = None
        live = len(self._sessions) - (old is not None)
        if live >= max_sessions:
            self._expire_now()
            live = len(self._sessions) - (old is not None and old.session_id in self._sessions)
            if live >= max_sessions:
                raise TooManySessions(max_sessions)
        superseded = None
        if old is not None and old.session_id in self._sessions:
            del self._sessions[old.session_id]
            self._superseded[old.session_id] = Supersession(
                old.session_id, record.session_id, old.token_hash, self.clock()
            )
            self._prune_supersessions()
            superseded = old.session_id
        self._tracks.pop(record.vehicle_id, None)
        self._live[record.vehicle_id] = record.session_id
        self._sessions[record.session_id] = self._copy(record)
        return superseded

    def _prune_supersessions(self) -> None:
        now = self.clock()
        stale = [sid for sid, entry in self._superseded.items() if now - entry.at > self.ttl_s]
        for sid in stale:
            del self._superseded[sid]

    async def live_session(self, vehicle_id: str) -> str | None:
        session_id = self._live.get(vehicle_id)
        if session_id is None or await self.get(session_id) is None:
            return None
        return session_id

    async def supersession(self, session_id: str) -> Supersession | None:
        entry = self._superseded.get(session_id)
        if entry is None or self.clock() - entry.at > self.ttl_s:
            return None
        return entry

    async def list_sessions(
        self,
        *,
        after: str | None = None,
        limit: int = 100,
        pipeline: str | None = None,
        vehicle_id: str | None = None,
    ) -> list[SessionSummary]:
        self._expire_now()
        found: list[SessionSummary] = []
        if limit < 1:
            return found
        for session_id in sorted(self._sessions):
            record = self._sessions[session_id]
            if after is not None and session_id <= after:
                continue
            if pipeline is not None and record.pipeline != pipeline:
                continue
            if vehicle_id is not None and record.vehicle_id != vehicle_id:
                continue
            found.append(SessionSummary.of(record))
            if len(found) >= limit:
                break
        return found

    async def get(self, session_id: str, *, with_response: bool = True) -> SessionRecord | None:
        record = self._sessions.get(session_id)
        if record is None:
            return None
        if self.is_expired(record, self.clock()):
            del self._sessions[session_id]
            return None
        return self._copy(record)

    async def compare_and_set(
        self, record: SessionRecord, expected_version: int, fixes: Sequence[NewFix] = ()
    ) -> bool:
        refuse_fixes_in_write(fixes)
        current = self._sessions.get(record.session_id)
        if current is None or current.version != expected_version:
            return False
        self._sessions[record.session_id] = self._copy(record, expected_version + 1)
        return True

    async def delete(self, session_id: str) -> bool:
        record = self._sessions.pop(session_id, None)
        if record is None:
            return False
        if self._live.get(record.vehicle_id) == session_id:
            del self._live[record.vehicle_id]
            self._tracks.pop(record.vehicle_id, None)
        return True

    async def count(self) -> int:
        self._expire_now()
        return len(self._sessions)

    async def expire(self) -> int:
        return self._expire_now()

    def _expire_now(self) -> int:
        now = self.clock()
        stale = [sid for sid, record in self._sessions.items() if self.is_expired(record, now)]
        for sid in stale:
            record = self._sessions.pop(sid)
            if self._live.get(record.vehicle_id) == sid:
                del self._live[record.vehicle_id]
        self._prune_supersessions()
        return len(stale)

    async def add_vehicles(self, vehicles: Sequence[VehicleRecord]) -> list[str]:
        new = [v for v in vehicles if v.vehicle_id not in self._vehicles]
        taken = any(self._vehicle_of_key.get(v.key_hash, v.vehicle_id) != v.vehicle_id for v in new)
        if taken or len({v.key_hash for v in new}) != len(new):
            raise ValueError("a key hash given is already another vehicle's")
        added = []
        for vehicle in vehicles:
            if vehicle.vehicle_id in self._vehicles:
                continue
            self._vehicles[vehicle.vehicle_id] = vehicle
            self._vehicle_of_key[vehicle.key_hash] = vehicle.vehicle_id
            added.append(vehicle.vehicle_id)
        return added

    async def get_vehicle(self, vehicle_id: str) -> VehicleRecord | None:
        return self._vehicles.get(vehicle_id)

    async def vehicle_of_key(self, key_hash: str) -> str | None:
        return self._vehicle_of_key.get(key_hash)

    async def list_vehicles(self, *, after: str | None = None, limit: int = 100) -> list[VehicleRecord]:
        ids = sorted(vid for vid in self._vehicles if after is None or vid > after)
        return [self._vehicles[vid] for vid in ids[:limit]]

    async def count_vehicles(self) -> int:
        return len(self._vehicles)

    async def rotate_vehicle_key(self, vehicle_id: str, key_hash: str, now: float) -> VehicleRecord | None:
        vehicle = self._vehicles.get(vehicle_id)
        if vehicle is None:
            return None
        if self._vehicle_of_key.get(key_hash, vehicle_id) != vehicle_id:
            raise ValueError("that key hash is already another vehicle's")
        self._vehicle_of_key.pop(vehicle.key_hash, None)
        rotated = dataclasses.replace(vehicle, key_hash=key_hash, key_issued_at=now)
        self._vehicles[vehicle_id] = rotated
        self._vehicle_of_key[key_hash] = vehicle_id
        return rotated

    async def delete_vehicle(self, vehicle_id: str) -> Revocation | None:
        vehicle = self._vehicles.pop(vehicle_id, None)
        if vehicle is None:
            return None
        self._vehicle_of_key.pop(vehicle.key_hash, None)
        session_id = self._live.pop(vehicle_id, None)
        ended = None
        record = self._sessions.pop(session_id, None) if session_id is not None else None
        if record is not None and not self.is_expired(record, self.clock()):
            ended = session_id
        self._tracks.pop(vehicle_id, None)
        return Revocation(vehicle_id, ended)

    async def upsert_rsus(self, rsus: Iterable[Rsu]) -> int:
        written = 0
        for rsu in rsus:
            self._rsus[rsu.id] = rsu
            written += 1
        return written

    async def get_rsu(self, rsu_id: str) -> Rsu | None:
        return self._rsus.get(rsu_id)

    async def get_rsus(self, rsu_ids: Iterable[str]) -> Mapping[str, Rsu]:
        return {rsu_id: self._rsus[rsu_id] for rsu_id in set(rsu_ids) if rsu_id in self._rsus}

    async def list_rsus(self) -> list[Rsu]:
        return [self._rsus[key] for key in sorted(self._rsus)]

    async def delete_rsu(self, rsu_id: str) -> bool:
        return self._rsus.pop(rsu_id, None) is not None

    async def put_ephemerides(self, document: StoredEphemerides) -> None:
        self._ephemerides = document

    async def get_ephemerides(self) -> StoredEphemerides | None:
        return self._ephemerides

    async def ephemerides_digest(self) -> str | None:
        return None if self._ephemerides is None else self._ephemerides.digest

    async def delete_ephemerides(self) -> bool:
        existed, self._ephemerides = self._ephemerides is not None, None
        return existed

    async def add_base_station(self, station: StoredBaseStation) -> bool:
        if station.station_id in self._base_stations:
            return False
        self._base_stations[station.station_id] = station
        self._base_epochs[station.station_id] = {}
        return True

    async def replace_base_station(self, station: StoredBaseStation) -> bool:
        if station.station_id not in self._base_stations:
            return False
        self._base_stations[station.station_id] = station
        return True

    async def get_base_station(self, station_id: str) -> StoredBaseStation | None:
        return self._base_stations.get(station_id)

    async def list_base_stations(self) -> list[StoredBaseStation]:
        return [self._base_stations[key] for key in sorted(self._base_stations)]

    async def delete_base_station(self, station_id: str) -> bool:
        self._base_epochs.pop(station_id, None)
        return self._base_stations.pop(station_id, None) is not None

    async def add_base_epochs(
        self, station_id: str, epochs: Sequence[tuple[float, str]], keep: int
    ) -> int | None:
        window = self._base_epochs.get(station_id)
        if window is None:
            return None
        window.update((float(gpst), document) for gpst, document in epochs)
        for gpst in sorted(window)[: max(0, len(window) - keep)]:
            del window[gpst]
        return len(window)

    async def base_window(self, station_id: str, since: float, until: float) -> BaseWindow | None:
        station = self._base_stations.get(station_id)
        if station is None:
            return None
        window = self._base_epochs[station_id]
        times = sorted(window)
        before = [t for t in times if t < since][-1:]
        chosen = before + [t for t in times if since <= t <= until]
        return BaseWindow(station, tuple((t, window[t]) for t in chosen))

    async def put_track(self, track: NeighbourTrack, session_id: str) -> bool:
        record = self._sessions.get(session_id)
        live = self._live.get(track.vehicle_id) == session_id
        if not live or record is None or self.is_expired(record, self.clock()):
            return False
        self._tracks[track.vehicle_id] = (track, self.clock())
        return True

    async def get_tracks(self, vehicle_ids: Iterable[str]) -> Mapping[str, NeighbourTrack]:
        now = self.clock()
        found = {}
        for vehicle_id in set(vehicle_ids):
            entry = self._tracks.get(vehicle_id)
            if entry is not None and self.track_is_live(entry[1], now):
                found[vehicle_id] = entry[0]
        return found

    async def delete_track(self, vehicle_id: str) -> bool:
        return self._tracks.pop(vehicle_id, None) is not None

    async def take_request(self, key: str, limit: RateLimit) -> float:
        now = self.clock()
        wait, tat = gcra(self._rate_tats.get(key), now, limit)
        if tat is None:
            return wait
        if len(self._rate_tats) >= _RATE_ENTRIES_BEFORE_PRUNING and key not in self._rate_tats:
            self._rate_tats = {k: v for k, v in self._rate_tats.items() if v > now}
        self._rate_tats[key] = tat
        return 0.0

    async def request_wait(self, key: str, limit: RateLimit) -> float:
        return gcra(self._rate_tats.get(key), self.clock(), limit)[0]

    async def put_document(self, kind: str, key: str, text: str) -> None:
        self._documents.setdefault(kind, {})[key] = text

    async def replace_document(self, kind: str, key: str, text: str) -> bool:
        documents = self._documents.get(kind, {})
        if key not in documents:
            return False
        documents[key] = text
        return True

    async def get_document(self, kind: str, key: str) -> str | None:
        return self._documents.get(kind, {}).get(key)

    async def list_documents(self, kind: str) -> dict[str, str]:
        documents = self._documents.get(kind, {})
        return {key: documents[key] for key in sorted(documents)}

    async def delete_document(self, kind: str, key: str) -> bool:
        return self._documents.get(kind, {}).pop(key, None) is not None

    def fix_log(self, buffer: int) -> FixLog:
        return AppendedFixLog(buffer)

    async def acquire_lease(self, name: str, owner: str, ttl_s: float) -> bool:
        now = self.clock()
        holder = self._leases.get(name)
        if holder is not None and holder[0] != owner and holder[1] > now:
            return False
        self._leases[name] = (owner, now + ttl_s)
        return True
