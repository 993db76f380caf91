"""The site's broadcast ephemerides on the service side: upload checks, the per-worker parsed cache, the
summary shown by ``GET /v1/ephemerides``, and the batch check that every pseudorange has a satellite state.

The navigation file itself lives in the session store (every worker and replica sees the same one); each
worker keeps the parsed form keyed by the file's SHA-256, so a batch costs one small digest read from the
store and no parsing while the file is unchanged.
"""

from __future__ import annotations

import asyncio
import hashlib
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from edgepos.api.schemas import EphemeridesOut, GpsTimeOut, ProblemModel
from edgepos.core.observations import Observation, PseudorangeObservation
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.orbits import MAX_AGE_S
from edgepos.gnss.rinex_nav import RinexError, parse_navigation
from edgepos.gnss.timesys import SECONDS_PER_WEEK
from edgepos.store.base import SessionStore, StoredEphemerides

CACHE_SIZE = 2
"""Parsed files kept per worker: the current one and the one before (batches in flight during a swap)."""


@dataclass(frozen=True)
class LoadedEphemerides:
    """A parsed navigation file: what the pipeline uses (healthy records) and, to tell a satellite without
    any ephemeris from an unhealthy one, the validity windows (GPS s) of every Keplerian record by
    satellite, healthy or not (the same windows ``BroadcastOrbits.select`` applies)."""

    ephemerides: Ephemerides
    windows: Mapping[tuple[str, int], tuple[tuple[float, float], ...]]
    size_bytes: int
    uploaded_at: float

    def covers(self, system: str, prn: int, gpst: float) -> bool:
        """Whether some record of the satellite is valid at ``gpst``."""
        return any(start <= gpst <= end for start, end in self.windows.get((system, prn), ()))


class NavigationFileError(ValueError):
    """An upload that is not a usable RINEX 3 navigation file; ``line`` is 1-based, or None."""

    def __init__(self, line: int | None, reason: str) -> None:
        super().__init__(reason)
        self.line = line
        self.reason = reason


def decode_upload(body: bytes) -> str:
    """The body as text: RINEX is ASCII; UTF-8 is accepted (comments may carry names with accents), and
    a byte-order mark some editors write is dropped."""
    try:
        return body.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as error:
        line = body[: error.start].count(b"\n") + 1
        raise NavigationFileError(line, f"byte {error.start} is not text (RINEX is ASCII)") from None


def parse(text: str, digest: str, uploaded_at: float) -> LoadedEphemerides:
    """Parse and check a navigation file (raises NavigationFileError naming the line and reason)."""
    try:
        navigation = parse_navigation(text.splitlines())
    except RinexError as error:
        reason = str(error).split(": ", 1)[1] if ": " in str(error) else str(error)
        raise NavigationFileError(error.line_number, reason) from None
    ephemerides = Ephemerides.from_navigation(navigation, digest)
    if len(ephemerides.orbits) == 0:
        found = ", ".join(f"{count} {system}" for system, count in sorted(navigation.skipped.items()))
        raise NavigationFileError(
            None,
            "no healthy GPS, BeiDou or Galileo ephemeris in the file"
            + (f" (only records of {found}, which are not used)" if found else ""),
        )
    windows: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for record in navigation.ephemerides:
        limit = MAX_AGE_S.get(record.system)
        if limit is None and record.system not in MAX_AGE_S:
            continue  # a system the orbit code does not evaluate (BroadcastOrbits skips it too)
        half = record.fit_interval_s / 2.0 if limit is None else limit
        windows.setdefault((record.system, record.prn), []).append((record.toe - half, record.toe + half))
    frozen = {sat: tuple(spans) for sat, spans in windows.items()}
    return LoadedEphemerides(ephemerides, frozen, len(text.encode()), uploaded_at)


def digest_of(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


class EphemeridesCache:
    """Parsed navigation files of this worker by digest, most recent last."""

    def __init__(self, capacity: int = CACHE_SIZE) -> None:
        self.capacity = capacity
        self._by_digest: OrderedDict[str, LoadedEphemerides] = OrderedDict()
        self._lock = asyncio.Lock()

    def remember(self, loaded: LoadedEphemerides) -> None:
        self._by_digest[loaded.ephemerides.digest] = loaded
        self._by_digest.move_to_end(loaded.ephemerides.digest)
        while len(self._by_digest) > self.capacity:
            self._by_digest.popitem(last=False)

    async def current(self, store: SessionStore, run: Any) -> LoadedEphemerides | None:
        """The store's navigation file, parsed (``run`` runs the parse off the event loop); None if none.

        A file that was accepted by PUT parses again, so a parse failure here means the stored text was
        changed behind the service's back: it propagates (a 500 that the logs show)."""
        digest = await store.ephemerides_digest()
        if digest is None:
            return None
        cached = self._by_digest.get(digest)
        if cached is not None:
            return cached
        async with self._lock:  # one parse per worker when many batches arrive right after an upload
            cached = self._by_digest.get(digest)
            if cached is not None:
                return cached
            stored = await store.get_ephemerides()
            if stored is None:
                return None
            loaded: LoadedEphemerides = await run(parse, stored.text, stored.digest, stored.uploaded_at)
            self.remember(loaded)
            return loaded


def _gps_time(seconds: float | None) -> GpsTimeOut | None:
    if seconds is None:
        return None
    week = int(seconds // SECONDS_PER_WEEK)
    return GpsTimeOut(week=week, tow=seconds - week * SECONDS_PER_WEEK, gps_seconds=seconds)


def summary(loaded: LoadedEphemerides) -> EphemeridesOut:
    """What GET/PUT /v1/ephemerides answer."""
    ephemerides = loaded.ephemerides
    facts: Mapping[str, Any] = ephemerides.summary()
    satellites = list(facts["satellites"])
    window = ephemerides.validity()
    return EphemeridesOut(
        digest=ephemerides.digest,
        size_bytes=loaded.size_bytes,
        uploaded_at=loaded.uploaded_at,
        systems=sorted({sat[0] for sat in satellites}),
        satellite_count=len(satellites),
        satellites=satellites,
        records=dict(sorted(facts["records"].items())),
        healthy_records=int(facts["healthy_records"]),
        skipped_records=dict(sorted(facts["skipped_records"].items())),
        valid_from=_gps_time(None if window is None else window[0]),
        valid_until=_gps_time(None if window is None else window[1]),
        ionosphere=list(facts["ionosphere"]),
        klobuchar=ephemerides.navigation.klobuchar_gps is not None,
    )


def stored_document(text: str, now: float) -> StoredEphemerides:
    return StoredEphemerides(digest_of(text), text, now)


def satellite_problems(
    observations: Sequence[Observation],
    loaded: LoadedEphemerides | None,
    systems_used: Sequence[str] | None,
) -> list[ProblemModel]:
    """Every pseudorange whose satellite state the service cannot know: no sat_position + sat_clock from
    the client and no ephemeris record of that satellite valid at its time (or none loaded at all); and
    every second pseudorange of one satellite in one epoch (a receiver reports one per signal, and the
    service uses one signal per constellation).

    Pseudoranges of constellations the session does not use (``systems_used``) need nothing. A record that
    exists but is unhealthy is not a problem of the request: the pipeline reports that pseudorange unused."""
    problems: list[ProblemModel] = []
    pending: list[tuple[int, PseudorangeObservation]] = []
    first_of: dict[tuple[float, str, int], int] = {}
    for index, observation in enumerate(observations):
        if not isinstance(observation, PseudorangeObservation):
            continue
        key = (observation.t, observation.system, observation.prn)
        if key in first_of:
            sat = f"{observation.system}{observation.prn:02d}"
            problems.append(
                ProblemModel(
                    index=index,
                    field=f"measurements[{index}].prn",
                    reason=f"{sat} already has a pseudorange at t={observation.t!r} "
                    f"(measurements[{first_of[key]}]); send one per satellite and epoch",
                )
            )
            continue
        first_of[key] = index
        if systems_used is not None and observation.system not in systems_used:
            continue
        has_position, has_clock = observation.sat_position is not None, observation.sat_clock is not None
        if has_position != has_clock:
            missing = "sat_clock" if has_position else "sat_position"
            problems.append(
                ProblemModel(
                    index=index,
                    field=f"measurements[{index}].{missing}",
                    reason="sat_position and sat_clock go together: send both or neither",
                )
            )
        elif not has_position:
            pending.append((index, observation))
    if not pending:
        return problems
    if loaded is None:
        for index, _ in pending:
            problems.append(
                ProblemModel(
                    index=index,
                    field=f"measurements[{index}].sat_position",
                    reason="no ephemerides are loaded on this server (an operator uploads them with "
                    "PUT /v1/ephemerides); without them send sat_position and sat_clock",
                )
            )
        return problems
    ephemerides = loaded.ephemerides
    by_time: dict[float, list[tuple[int, PseudorangeObservation]]] = {}
    for index, observation in pending:
        by_time.setdefault(observation.t, []).append((index, observation))
    for t, group in by_time.items():
        gpst = ephemerides.gpst(t)
        for index, observation in group:
            if not loaded.covers(observation.system, observation.prn, gpst):
                sat = f"{observation.system}{observation.prn:02d}"
                week = int(gpst // SECONDS_PER_WEEK)
                problems.append(
                    ProblemModel(
                        index=index,
                        field=f"measurements[{index}].prn",
                        reason=f"the loaded ephemerides have no record of {sat} valid at GPS week {week} "
                        f"second {t:.1f} (see GET /v1/ephemerides for the satellites and validity window); "
                        "leave it out or send sat_position and sat_clock",
                    )
                )
    problems.sort(key=lambda problem: problem.index if problem.index is not None else -1)
    return problems
