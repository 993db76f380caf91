"""The vehicles' latest fixes as the location adapter reads them, and their MEC 013 LocationInfo.

The source is each live session's ``last_fix`` (the last fix of its last applied batch, in the session
record): it is written in the same compare-and-set as the batch, so every worker and every store
(memory, SQLite, Redis, Redis Cluster) reads the same latest fix, and it goes with the session (ended,
superseded or expired). ``updated_at`` of the record is when the server applied that batch: it is
the fix's time in this adapter (the fix's own ``t`` is the vehicle's clock, not a wall clock).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from edgepos.api.location.schemas import LocationInfo, TimeStamp, Velocity
from edgepos.core.zones import bearing_deg, circle_accuracy
from edgepos.geo import GeodeticOrigin
from edgepos.store.base import SessionStore

ADDRESS_PREFIX = "acr:"
PAGE = 1000
_UNUSABLE = ("uninitialised", "diverged")


def address_of(vehicle_id: str) -> str:
    return ADDRESS_PREFIX + vehicle_id


def vehicle_of(address: str) -> str:
    """The vehicle id of an ``acr:`` address (the caller has checked the form)."""
    return address[len(ADDRESS_PREFIX) :]


def timestamp(at: float) -> TimeStamp:
    """Unix seconds as a MEC 013 TimeStamp."""
    seconds = math.floor(at)
    return TimeStamp(seconds=seconds, nanoSeconds=min(999_999_999, round((at - seconds) * 1e9)))


@dataclass(frozen=True)
class LatestFix:
    """A vehicle's latest fix: the wire fix (FixOut as JSON) and when the server applied it (Unix s)."""

    vehicle_id: str
    at: float
    fix: dict[str, Any]

    @property
    def usable(self) -> bool:
        """Whether the fix has a position to use (not uninitialised, not diverged)."""
        return self.fix.get("status") not in _UNUSABLE and self.fix.get("x") is not None

    @property
    def xy(self) -> tuple[float, float]:
        return float(self.fix["x"]), float(self.fix["y"])

    def accuracy_m(self) -> float:
        covariance = self.fix.get("position_covariance")
        return 0.0 if covariance is None else circle_accuracy(covariance)

    def location_info(self, origin: GeodeticOrigin) -> LocationInfo:
        """The fix in MEC 013 terms (degrees, km/h); call only when ``usable``."""
        fix = self.fix
        if fix.get("latitude") is not None and fix.get("longitude") is not None:
            lat, lon = float(fix["latitude"]), float(fix["longitude"])  # the pipeline's own (rad)
        else:
            lat, lon, _ = origin.enu_to_geodetic(*self.xy)
        velocity = None
        if fix.get("vx") is not None and fix.get("vy") is not None:
            vx, vy = float(fix["vx"]), float(fix["vy"])
            velocity = Velocity(
                bearing=round(bearing_deg(vx, vy)) % 360, horizontalSpeed=round(math.hypot(vx, vy) * 3.6)
            )
        return LocationInfo(
            latitude=[math.degrees(lat)],
            longitude=[math.degrees(lon)],
            altitude=None if fix.get("height") is None else float(fix["height"]),
            accuracy=math.ceil(self.accuracy_m()),
            velocity=velocity,
            timestamp=timestamp(self.at),
        )


def _latest(vehicle_id: str, at: float, last_fix: str | None) -> LatestFix | None:
    return None if last_fix is None else LatestFix(vehicle_id, at, json.loads(last_fix))


async def latest_fixes(store: SessionStore, vehicle_ids: Iterable[str] | None = None) -> dict[str, LatestFix]:
    """The latest fix of each vehicle with a live session that has one, by vehicle id (sorted); with
    ``vehicle_ids`` only those vehicles' (read by their live-session pointers, not by a full listing)."""
    found: dict[str, LatestFix] = {}
    if vehicle_ids is not None:
        for vehicle_id in sorted(set(vehicle_ids)):
            session_id = await store.live_session(vehicle_id)
            record = None if session_id is None else await store.get(session_id)
            latest = None if record is None else _latest(vehicle_id, record.updated_at, record.last_fix)
            if latest is not None:
                found[vehicle_id] = latest
        return found
    after = None
    while True:
        page = await store.list_sessions(after=after, limit=PAGE)
        for summary in page:
            latest = _latest(summary.vehicle_id, summary.updated_at, summary.last_fix)
            if latest is not None:
                found[summary.vehicle_id] = latest
        if len(page) < PAGE:
            return dict(sorted(found.items()))
        after = page[-1].session_id
