"""The site's reference stations on the service side: registrations as stored, base observations (RINEX 3
or RTCM 3) turned into per-epoch corrections for the store, and the corrections a gnss_tight batch uses.

Corrections are computed once, at upload, with the ephemerides loaded then (gnss/differential.py); each
stored epoch keeps the ephemeris issue (IODE, toe) of every satellite, so a rover whose ephemeris differs is
told so per pseudorange instead of getting a correction of another orbit. A batch reads, in one store call,
only the epochs it can use: from its first epoch minus the session's maximum correction age to its last, and
the newest one before that (which lets a pseudorange be told its correction is too old).
"""

from __future__ import annotations

import json
import math
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from edgepos.api.errors import ApiError
from edgepos.api.schemas import ProblemModel
from edgepos.core.observations import Observation, PseudorangeObservation
from edgepos.geo import geodetic_to_ecef
from edgepos.gnss import geodesy
from edgepos.gnss.differential import (
    DEFAULT_MAX_AGE_S,
    CorrectionTable,
    EpochCorrections,
    epoch_corrections,
)
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.geodesy import enu_rotation
from edgepos.gnss.measurements import STATION_GALILEO_GROUP_DELAY, without_group_delay
from edgepos.gnss.rinex_nav import RinexError
from edgepos.gnss.rinex_obs import DEFAULT_CODES, ObservationEpoch, iter_epochs
from edgepos.gnss.timesys import SECONDS_PER_WEEK
from edgepos.pipelines.gnss_options import NEAREST_BASE_STATION
from edgepos.store.base import SessionStore, StoredBaseStation

ELEVATION_MASK_RAD = math.radians(10.0)
"""The base's mask: what the estimation half measured with (eval gnss-rinex --base, default mask)."""


@dataclass(frozen=True)
class Station:
    """A registration: the marker as surveyed, the antenna delta (up, east, north m), where the position came
    from and the receiver's Galileo group delay; the corrections use the antenna reference point
    :attr:`position_ecef`."""

    station_id: str
    marker_ecef: tuple[float, float, float] | None
    antenna_delta: tuple[float, float, float] | None
    position_source: str | None
    updated_at: float
    galileo_group_delay: str = STATION_GALILEO_GROUP_DELAY
    """What the station receiver's Galileo code carries of the satellite group delay (``gnss.measurements``)."""

    @property
    def position_ecef(self) -> np.ndarray | None:
        if self.marker_ecef is None:
            return None
        marker = np.asarray(self.marker_ecef, dtype=float)
        if self.antenna_delta is None:
            return marker
        up, east, north = self.antenna_delta  # as differential.base_position turns a RINEX header's
        lat, lon, _ = geodesy.ecef_to_geodetic(marker)
        position: np.ndarray = marker + enu_rotation(float(lat), float(lon)).T @ np.array([east, north, up])
        return position

    def stored(self) -> StoredBaseStation:
        document = {
            "marker_ecef": None if self.marker_ecef is None else list(self.marker_ecef),
            "antenna_delta": None if self.antenna_delta is None else list(self.antenna_delta),
            "position_source": self.position_source,
            "galileo_group_delay": self.galileo_group_delay,
        }
        return StoredBaseStation(self.station_id, json.dumps(document), self.updated_at)

    @classmethod
    def of(cls, stored: StoredBaseStation) -> Station:
        document = json.loads(stored.document)
        marker, delta = document.get("marker_ecef"), document.get("antenna_delta")
        return cls(
            stored.station_id,
            None if marker is None else (float(marker[0]), float(marker[1]), float(marker[2])),
            None if delta is None else (float(delta[0]), float(delta[1]), float(delta[2])),
            document.get("position_source"),
            stored.updated_at,
            document.get("galileo_group_delay", STATION_GALILEO_GROUP_DELAY),  # registered before: broadcast
        )


def marker_from_geodetic(latitude: float, longitude: float, height: float) -> tuple[float, float, float]:
    return geodetic_to_ecef(latitude, longitude, height)


# -- stored epochs --------------------------------------------------------------------------------
def epoch_document(epoch: EpochCorrections) -> str:
    """One base epoch's corrections as JSON (floats round-trip exactly)."""
    return json.dumps(
        {
            "gpst": epoch.gpst,
            "sats": list(epoch.sats),
            "correction_m": [float(v) for v in epoch.correction_m],
            "iode": [issue[0] for issue in epoch.issues],
            "toe": [issue[1] for issue in epoch.issues],
            "ionosphere_m": [float(v) for v in epoch.ionosphere_m],
            "troposphere_m": [float(v) for v in epoch.troposphere_m],
        },
        allow_nan=False,
    )


def epoch_of(document: str) -> EpochCorrections:
    value = json.loads(document)
    return EpochCorrections(
        float(value["gpst"]),
        tuple(value["sats"]),
        np.asarray(value["correction_m"], dtype=float),
        tuple((int(iode), float(toe)) for iode, toe in zip(value["iode"], value["toe"])),
        np.asarray(value["ionosphere_m"], dtype=float),
        np.asarray(value["troposphere_m"], dtype=float),
    )


class EpochCache:
    """Decoded stored epochs of this worker, keyed by their document (so a replaced epoch is decoded
    again): consecutive batches of a session read mostly the same epochs, and decoding them is most of
    a batch's correction cost. Least recently used first out."""

    def __init__(self, capacity: int = 4096) -> None:
        self.capacity = capacity
        self._decoded: OrderedDict[tuple[str, float, str], EpochCorrections] = OrderedDict()

    def decode(self, station_id: str, gpst: float, document: str) -> EpochCorrections:
        key = (station_id, gpst, document)
        found = self._decoded.get(key)
        if found is None:
            found = self._decoded[key] = epoch_of(document)
            while len(self._decoded) > self.capacity:
                self._decoded.popitem(last=False)
        else:
            self._decoded.move_to_end(key)
        return found


def needed_rows(epochs: Sequence[EpochCorrections], times: Sequence[float]) -> list[EpochCorrections]:
    """Only the rows a lookup at one of the rover ``times`` can return: per rover time and satellite the
    newest row at or before it (as CorrectionTable.lookup picks, with its 1 us tolerance). The table built
    from them answers every lookup at those times exactly as one built from all ``epochs`` would."""
    keep: dict[int, set[str]] = {}
    for t in times:
        seen: set[str] = set()
        for index in range(len(epochs) - 1, -1, -1):
            epoch = epochs[index]
            if epoch.gpst > t + 1e-6:
                continue
            fresh = set(epoch.sats) - seen
            if fresh:
                keep.setdefault(index, set()).update(fresh)
                seen |= fresh
    out = []
    for index in sorted(keep):
        epoch, wanted = epochs[index], keep[index]
        if len(wanted) == len(epoch.sats):
            out.append(epoch)
            continue
        rows = [k for k, sat in enumerate(epoch.sats) if sat in wanted]
        out.append(
            EpochCorrections(
                epoch.gpst,
                tuple(epoch.sats[k] for k in rows),
                epoch.correction_m[rows],
                tuple(epoch.issues[k] for k in rows),
                epoch.ionosphere_m[rows],
                epoch.troposphere_m[rows],
            )
        )
    return out


# -- uploads ----------------------------------------------------------------------------------------
class ObservationFileError(ValueError):
    """An upload that is not a usable RINEX 3 observation file; ``line`` is 1-based, or None."""

    def __init__(self, line: int | None, reason: str) -> None:
        super().__init__(reason)
        self.line = line
        self.reason = reason


def parse_observations(text: str) -> list[ObservationEpoch]:
    """The GPS (C1C), BeiDou (C2I) and Galileo (C1C) pseudorange epochs of a RINEX 3 observation file."""
    try:
        return [epoch for _, epoch in iter_epochs(text.splitlines(), None)]
    except RinexError as error:
        reason = str(error).split(": ", 1)[1] if ": " in str(error) else str(error)
        raise ObservationFileError(error.line_number, reason) from None
    except (ValueError, IndexError) as error:
        raise ObservationFileError(None, f"not a RINEX 3 observation file ({error})") from None


def corrections_of(
    epochs: Sequence[ObservationEpoch],
    position: np.ndarray,
    ephemerides: Ephemerides,
    galileo_group_delay: str = STATION_GALILEO_GROUP_DELAY,
) -> list[EpochCorrections]:
    """The corrections of every epoch that has some (others, e.g. outside the ephemerides, are dropped),
    with the station receiver's Galileo group delay."""
    found = []
    no_group_delay = without_group_delay(galileo_group_delay)
    for epoch in epochs:
        corrections = epoch_corrections(
            epoch,
            position,
            ephemerides.orbits,
            ephemerides.atmosphere,
            DEFAULT_CODES,
            ELEVATION_MASK_RAD,
            no_group_delay,
        )
        if corrections.sats:
            found.append(corrections)
    return found


# -- a batch's corrections --------------------------------------------------------------------------
def _session_position(last_fix: str | None, origin: tuple[float, float, float] | None) -> np.ndarray | None:
    """Where the session is for 'nearest': its last fix, else the site origin, else unknown."""
    if last_fix is not None:
        fix = json.loads(last_fix)
        lat, lon, height = fix.get("latitude"), fix.get("longitude"), fix.get("height")
        if lat is not None and lon is not None:
            return np.asarray(geodetic_to_ecef(lat, lon, height or 0.0))
    if origin is not None:
        return np.asarray(geodetic_to_ecef(*origin))
    return None


def nearest(stations: Sequence[Station], position: np.ndarray) -> Station | None:
    """The station with a position nearest ``position`` (ECEF m); ties go to the smaller id."""
    located = [
        (float(np.linalg.norm(s.position_ecef - position)), s.station_id, s)
        for s in stations
        if s.marker_ecef
    ]
    return min(located, key=lambda item: item[:2])[2] if located else None


def _rover_times(
    observations: Sequence[Observation], options: Mapping[str, Any], ephemerides: Ephemerides | None
) -> list[float] | None:
    """Continuous GPS seconds of the batch's pseudorange epochs, as the pipeline will compute them."""
    tows = sorted({o.t for o in observations if isinstance(o, PseudorangeObservation)})
    if ephemerides is not None:
        return [ephemerides.gpst(t) for t in tows]
    week = options.get("gps_week")
    return None if week is None else [week * SECONDS_PER_WEEK + t for t in tows]


async def batch_corrections(
    store: SessionStore,
    cache: EpochCache,
    options: Mapping[str, Any],
    observations: Sequence[Observation],
    ephemerides: Ephemerides | None,
    last_fix: str | None,
    origin: tuple[float, float, float] | None,
) -> CorrectionTable | None:
    """The corrections a gnss_tight batch may use (None: the session asked for none). An empty table says
    per pseudorange why there are none (station gone, no position to find the nearest, no base epochs)."""
    wanted = options.get("base_station")
    if wanted is None:
        return None
    max_age = float(options.get("max_correction_age_s") or DEFAULT_MAX_AGE_S)

    def empty(reason: str) -> CorrectionTable:
        return CorrectionTable((), max_age, f"no base data: {reason}")

    times = _rover_times(observations, options, ephemerides)
    if not times:
        return empty("the batch's GPS week is unknown (no ephemerides loaded and no gps_week option)")
    if wanted == NEAREST_BASE_STATION:
        position = _session_position(last_fix, origin)
        if position is None:
            return empty("the session has no fix yet and the site no origin, so no station is nearest")
        station = nearest([Station.of(s) for s in await store.list_base_stations()], position)
        if station is None:
            return empty("no registered base station has a position")
        wanted = station.station_id
    window = await store.base_window(str(wanted), times[0] - max_age, times[-1])
    if window is None:
        return empty(f"base station {wanted!r} is not registered (deleted?)")
    if not window.epochs:
        return empty(f"base station {wanted!r} has no observations at or before this epoch")
    decoded = [cache.decode(str(wanted), gpst, document) for gpst, document in window.epochs]
    return CorrectionTable(
        needed_rows(decoded, times),
        max_age,
        f"no base data: base station {wanted!r} has no observations at or before this epoch",
    )


async def check_base_station(store: SessionStore, options: Mapping[str, Any]) -> None:
    """At session creation: the named station exists (404) and has a position (422); for 'nearest', some
    station has one (422). Later changes (a station deleted) are reported per pseudorange, not refused."""
    wanted = options.get("base_station")
    if wanted is None:
        return
    if wanted == NEAREST_BASE_STATION:
        if nearest([Station.of(s) for s in await store.list_base_stations()], np.zeros(3)) is None:
            reason = "no registered base station has a position (POST /v1/base-stations)"
            raise ApiError(
                "invalid_request",
                reason,
                [ProblemModel(index=None, field="options.base_station", reason=reason)],
            )
        return
    stored = await store.get_base_station(str(wanted))
    if stored is None:
        reason = f"no base station {wanted!r} is registered (GET /v1/base-stations lists them)"
        raise ApiError(
            "not_found", reason, [ProblemModel(index=None, field="options.base_station", reason=reason)]
        )
    if Station.of(stored).marker_ecef is None:
        reason = (
            f"base station {wanted!r} has no position yet: register it with one, or send its RTCM 1005/1006, "
            "before sessions use it"
        )
        raise ApiError(
            "invalid_request", reason, [ProblemModel(index=None, field="options.base_station", reason=reason)]
        )
