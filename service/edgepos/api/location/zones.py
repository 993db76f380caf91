"""The operator's zones (PUT /v1/zones/{zone_id}): validation, their stored form, and which zones hold a point.

A zone is kept as a store document (kind ``zones``) holding the zone as given and its shape in the site
frame: a WGS-84 zone is converted once, when it is written, with the site origin, so the notifier tests
fixes against plane shapes only.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from edgepos.api.errors import ApiError
from edgepos.api.location.schemas import CircleOut, SiteShapeOut, ZoneIn, ZoneOut
from edgepos.api.schemas import ProblemModel
from edgepos.core.zones import Circle, Polygon, Shape, polygon_self_intersects
from edgepos.geo import GeodeticOrigin
from edgepos.store.base import SessionStore

KIND = "zones"
MAX_ZONES = 1000


@dataclass(frozen=True)
class Zone:
    zone_id: str
    shape: Shape


def _invalid(field: str, reason: str) -> ApiError:
    return ApiError(
        "invalid_request",
        f"invalid {field}: {reason}",
        [ProblemModel(index=None, field=field, reason=reason)],
    )


def site_shape(zone: ZoneIn, origin: GeodeticOrigin | None) -> Shape:
    """The zone's shape in the site frame; 422 for a zone that is not one shape or not a simple polygon,
    409 for a WGS-84 zone without a site origin."""
    if (zone.circle is None) == (zone.polygon is None):
        raise _invalid("body", "give exactly one of circle and polygon")
    if zone.frame == "wgs84" and origin is None:
        raise ApiError(
            "conflict",
            "a zone in WGS-84 needs the site origin to be placed in the site frame: set EDGEPOS_ORIGIN_LAT and "
            "EDGEPOS_ORIGIN_LON, or give the zone in the site frame",
        )

    def to_site(point: list[float], field: str) -> tuple[float, float]:
        if zone.frame == "site":
            return point[0], point[1]
        assert origin is not None
        lat, lon = point
        if abs(lat) > 1.5707963267948966 or abs(lon) > 3.141592653589793:
            raise _invalid(
                field, "latitude must be within [-pi/2, pi/2] and longitude within [-pi, pi] (rad)"
            )
        east, north, _ = origin.geodetic_to_enu(lat, lon)
        if abs(east) > 1.0e6 or abs(north) > 1.0e6:
            raise _invalid(field, "is more than 1000 km from the site origin")
        return east, north

    if zone.circle is not None:
        x, y = to_site(zone.circle.center, "circle.center")
        return Circle(x, y, zone.circle.radius)
    assert zone.polygon is not None
    vertices = tuple(to_site(point, f"polygon[{i}]") for i, point in enumerate(zone.polygon))
    polygon = Polygon(vertices)
    if len(set(vertices)) < 3 or polygon.area() < 1e-6:
        raise _invalid("polygon", "needs at least 3 distinct vertices enclosing an area")
    if polygon_self_intersects(vertices):
        raise _invalid("polygon", "edges cross each other; give the vertices in order around the zone")
    return polygon


def encode_zone(zone_id: str, zone: ZoneIn, shape: Shape, now: float) -> str:
    site: dict[str, Any] = {"circle": None, "polygon": None}
    if isinstance(shape, Circle):
        site["circle"] = {"center": [shape.x, shape.y], "radius": shape.radius}
    else:
        site["polygon"] = [list(point) for point in shape.vertices]
    return json.dumps(
        {
            "zone_id": zone_id,
            "frame": zone.frame,
            "circle": None
            if zone.circle is None
            else {"center": list(zone.circle.center), "radius": zone.circle.radius},
            "polygon": None if zone.polygon is None else [list(point) for point in zone.polygon],
            "site": site,
            "updated_at": now,
        }
    )


def _circle_out(value: dict[str, Any] | None) -> CircleOut | None:
    return None if value is None else CircleOut(center=list(value["center"]), radius=value["radius"])


def _polygon_out(value: list[list[float]] | None) -> list[list[float]] | None:
    return None if value is None else [list(point) for point in value]


def zone_out(text: str) -> ZoneOut:
    value = json.loads(text)
    return ZoneOut(
        zone_id=value["zone_id"],
        frame=value["frame"],
        circle=_circle_out(value["circle"]),
        polygon=_polygon_out(value["polygon"]),
        site=SiteShapeOut(
            circle=_circle_out(value["site"]["circle"]), polygon=_polygon_out(value["site"]["polygon"])
        ),
        updated_at=value["updated_at"],
    )


def decode_zone(text: str) -> Zone:
    value = json.loads(text)
    site = value["site"]
    if site["circle"] is not None:
        (x, y), radius = site["circle"]["center"], site["circle"]["radius"]
        return Zone(value["zone_id"], Circle(x, y, radius))
    return Zone(value["zone_id"], Polygon(tuple((a, b) for a, b in site["polygon"])))


async def load_zones(store: SessionStore) -> dict[str, Zone]:
    """Every zone, by id (sorted)."""
    return {key: decode_zone(text) for key, text in (await store.list_documents(KIND)).items()}


def zones_holding(zones: dict[str, Zone], x: float, y: float) -> list[str]:
    """The ids of the zones that hold (x, y), in id order."""
    return [zone_id for zone_id, zone in zones.items() if zone.shape.contains(x, y)]
