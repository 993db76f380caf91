"""The default store: dicts in this process. Fast and simple; sessions are lost on restart and not
shared between worker processes (``edgepos serve --workers N`` refuses it for N > 1)."""

from __future__ import annotations

import copy
import dataclasses
import time
from collections.abc import Iterable, Mapping

from edgepos.pipelines.base import NeighbourTrack, Rsu
from edgepos.store.base import Clock, SessionRecord, SessionStore, StoredEphemerides, TooManySessions
from edgepos.store.ratelimit import RateLimit, gcra

#: Past this many rate-limit entries, entries whose budget is full again are dropped.
_RATE_ENTRIES_BEFORE_PRUNING = 4096


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

    @staticmethod
    def _copy(record: SessionRecord) -> SessionRecord:
        return dataclasses.replace(record, options=copy.deepcopy(record.options))

    async def create(self, record: SessionRecord, max_sessions: int) -> None:
        if record.session_id in self._sessions:
            raise ValueError(f"session {record.session_id!r} already exists")
        if len(self._sessions) >= max_sessions:
            self._expire_now()
            if len(self._sessions) >= max_sessions:
                raise TooManySessions(max_sessions)
        self._sessions[record.session_id] = self._copy(record)

    async def get(self, session_id: str) -> SessionRecord | None:
        record = self._sessions.get(session_id)
        if record is None:
            return None
        if self.is_expired(record, self.clock()):
            del self._sessions[session_id]
            return None
        return self._copy(record)

    async def compare_and_set(self, record: SessionRecord, expected_version: int) -> bool:
        current = self._sessions.get(record.session_id)
        if current is None or current.version != expected_version:
            return False
        self._sessions[record.session_id] = dataclasses.replace(
            self._copy(record), version=expected_version + 1
        )
        return True

    async def delete(self, session_id: str) -> bool:
        return self._sessions.pop(session_id, None) is not None

    async def count(self) -> int:
        self._expire_now()
        return len(self._sessions)

    async def expire(self) -> int:
        return self._expire_now()

    def _expire_now(self) -> int:
        now = self.clock()
        stale = [sid for sid, record in self._sessions.items() if self.is_expired(record, now)]
        for sid in stale:
            del self._sessions[sid]
        return len(stale)

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

    async def put_track(self, track: NeighbourTrack) -> None:
        self._tracks[track.vehicle_id] = (track, self.clock())

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
