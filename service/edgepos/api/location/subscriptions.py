"""Location subscriptions (MEC 013 user and zone location events): their stored documents, the check of
their callbacks, and how a document turns the vehicles' latest fixes into notifications.

A subscription is one store document (kind ``subscriptions``) holding what the client asked (the wire
subscription), which zones each watched vehicle was in at the last look (``members``), the
notifications not yet delivered (``pending``) and the delivery state (``failures``, ``retry_at``).
Only the notifier's lease holder updates a document after it is created (``replace_document``, which
never brings back a deleted one), so the state moves on wherever that holder runs.
"""

from __future__ import annotations

import json
import secrets
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from edgepos.api.errors import ApiError
from edgepos.api.location.fixes import LatestFix, address_of, timestamp
from edgepos.api.location.schemas import (
    LinkType,
    LocationEventType,
    SubscriptionLink,
    UserLocationEventNotification,
    ZoneLocationEventNotification,
)
from edgepos.api.location.zones import Zone, zones_holding
from edgepos.api.schemas import ProblemModel
from edgepos.geo import GeodeticOrigin

KIND = "subscriptions"
MAX_SUBSCRIPTIONS = 1000
MAX_PENDING = 100
"""Notifications one subscription keeps while its callback fails; beyond, the oldest are dropped (counted)."""
MAX_BACKOFF_S = 300.0
USERS, ZONES = "users", "zones"


def new_subscription_id() -> str:
    return secrets.token_hex(12)


def check_callback(url: str, hosts: frozenset[str]) -> None:
    """422 unless ``url`` is an http(s) URL on one of the allowed callback hosts (EDGEPOS_CALLBACK_HOSTS)."""
    problem = callback_problem(url, hosts)
    if problem is not None:
        raise ApiError(
            "invalid_request",
            f"invalid callbackReference: {problem}",
            [ProblemModel(index=None, field="callbackReference", reason=problem)],
        )


def callback_problem(url: str, hosts: frozenset[str]) -> str | None:
    """Why notifications may not go to ``url``, None when they may."""
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 -- raises ValueError for a port that is not a number in range
    except ValueError as error:
        return f"is not a valid URL ({error})"
    if parts.scheme not in ("http", "https") or not parts.hostname:
        return "must be an absolute http:// or https:// URL"
    if parts.username is not None or parts.password is not None:
        return "must not carry a user name or password"
    host = parts.hostname.lower()
    if host not in hosts:
        allowed = ", ".join(sorted(hosts))
        return f"host {host!r} is not an allowed callback host (EDGEPOS_CALLBACK_HOSTS: {allowed})"
    return None


def new_document(
    kind: str,
    subscription_id: str,
    wire: dict[str, Any],
    href: str,
    *,
    address: str | None,
    zone_id: str | None,
    vehicles: list[str] | None,
    events: list[str],
    expires_at: float | None,
    members: dict[str, list[str]],
    now: float,
) -> dict[str, Any]:
    return {
        "id": subscription_id,
        "kind": kind,
        "subscription": wire,
        "href": href,
        "callback": wire["callbackReference"],
        "address": address,
        "zone_id": zone_id,
        "vehicles": vehicles,
        "events": events,
        "expires_at": expires_at,
        "members": members,
        "pending": [],
        "dropped": 0,
        "failures": 0,
        "retry_at": 0.0,
        "created_at": now,
    }


def watched_vehicles(document: dict[str, Any]) -> list[str] | None:
    """The vehicles a subscription looks at, None for every vehicle."""
    if document["kind"] == USERS:
        return [document["address"]]
    vehicles: list[str] | None = document["vehicles"]
    return vehicles


def memberships(
    document: dict[str, Any], zones: dict[str, Zone], fixes: dict[str, LatestFix]
) -> dict[str, list[str]]:
    """Which of the subscription's zones each watched vehicle with a usable fix is in now (vehicles without
    one keep what they had: a fix that is missing for a moment is not a crossing)."""
    members: dict[str, list[str]] = {key: list(value) for key, value in document["members"].items()}
    vehicles = watched_vehicles(document)
    candidates = fixes.values() if vehicles is None else [fixes[v] for v in vehicles if v in fixes]
    for latest in candidates:
        if not latest.usable:
            continue
        inside = zones_holding(zones, *latest.xy)
        if document["kind"] == ZONES:
            inside = [zone_id for zone_id in inside if zone_id == document["zone_id"]]
        if inside:
            members[latest.vehicle_id] = inside
        else:
            members.pop(latest.vehicle_id, None)
    return members


@dataclass(frozen=True)
class Crossing:
    vehicle_id: str
    zone_id: str
    event: LocationEventType


def crossings(
    before: dict[str, list[str]], after: dict[str, list[str]], zones: dict[str, Zone]
) -> list[Crossing]:
    """Entries and exits between two membership maps (zones deleted meanwhile are left out)."""
    found = []
    for vehicle_id in sorted(set(before) | set(after)):
        old = {zone for zone in before.get(vehicle_id, []) if zone in zones}
        new = set(after.get(vehicle_id, []))
        found += [Crossing(vehicle_id, zone, "ENTERING_AREA_EVENT") for zone in sorted(new - old)]
        found += [Crossing(vehicle_id, zone, "LEAVING_AREA_EVENT") for zone in sorted(old - new)]
    return found


def notification(
    document: dict[str, Any],
    crossing: Crossing,
    fixes: dict[str, LatestFix],
    origin: GeodeticOrigin | None,
    now: float,
) -> dict[str, Any]:
    """The JSON body of the notification of one crossing."""
    links = SubscriptionLink(subscription=LinkType(href=document["href"]))
    address = address_of(crossing.vehicle_id)
    if document["kind"] == USERS:
        latest = fixes.get(crossing.vehicle_id)
        info = (
            latest.location_info(origin)
            if latest is not None and latest.usable and origin is not None
            else None
        )
        body: Any = UserLocationEventNotification(
            timeStamp=timestamp(now),
            address=address,
            eventType=crossing.event,
            zoneId=crossing.zone_id,
            locationInfo=info,
            links=links,
        )
    else:
        body = ZoneLocationEventNotification(
            timeStamp=timestamp(now),
            address=address,
            zoneId=crossing.zone_id,
            userLocationEvent=crossing.event,
            links=links,
        )
    result: dict[str, Any] = body.model_dump(mode="json", exclude_none=True)
    return result


def advance(
    document: dict[str, Any],
    zones: dict[str, Zone],
    fixes: dict[str, LatestFix],
    origin: GeodeticOrigin | None,
    now: float,
) -> bool:
    """Bring the document's memberships up to the latest fixes and queue a notification for each crossing
    of a kind it asked for; True when the document changed."""
    members = memberships(document, zones, fixes)
    if members == document["members"]:
        return False
    for crossing in crossings(document["members"], members, zones):
        if crossing.event in document["events"]:
            document["pending"].append(notification(document, crossing, fixes, origin, now))
    overflow = len(document["pending"]) - MAX_PENDING
    if overflow > 0:
        del document["pending"][:overflow]
        document["dropped"] += overflow
    document["members"] = members
    return True


def record_failure(document: dict[str, Any], now: float, backoff_s: float) -> None:
    """One more failed delivery: the next try waits ``backoff_s`` doubled per failure before it (capped)."""
    document["failures"] += 1
    document["retry_at"] = now + min(MAX_BACKOFF_S, backoff_s * 2.0 ** (document["failures"] - 1))


def encode(document: dict[str, Any]) -> str:
    return json.dumps(document, allow_nan=False)
