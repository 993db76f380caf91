"""Wire models of the location adapter: the ETSI GS MEC 013 (V3.1.1) resource shapes under /location/v3
and the operator's zones under /v1/zones.

The MEC models keep the specification's names (camelCase) and units: angles in **degrees** and speeds
in km/h where the specification says so. This adapter is the one documented exception to the
service's SI-units-and-radians rule, so that an unmodified MEC 013 client reads it; every such field
says so in its description. /v1/zones follows the service's rules (metres, radians).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import ConfigDict, Field

from edgepos.api.schemas import MAX_COORDINATE_M, RequestModel, ResponseModel, exactly_one_of

ADDRESS_PATTERN = r"^acr:[A-Za-z0-9._:+@/ -]{1,128}$"
"""A user's address: ``acr:`` and the vehicle id (the anonymous customer reference URI of MEC 013)."""
ZONE_ID_PATTERN = r"^[A-Za-z0-9._-]{1,64}$"
MAX_ZONE_RADIUS_M = 100_000.0
MAX_POLYGON_VERTICES = 100
DEGREES = (
    "Degrees, as ETSI GS MEC 013 mandates (this adapter is the documented exception to the service's "
    "SI/radians rule)"
)
LocationEventType = Literal["ENTERING_AREA_EVENT", "LEAVING_AREA_EVENT"]
LOCATION_EVENT_TYPES: tuple[LocationEventType, ...] = ("ENTERING_AREA_EVENT", "LEAVING_AREA_EVENT")


class MecModel(ResponseModel):
    """Base of the MEC response models: fields are written by their alias (``_links``, ``self``)."""

    model_config = ConfigDict(allow_inf_nan=False, populate_by_name=True, serialize_by_alias=True)


class TimeStamp(MecModel):
    """A time of the server's clock as MEC 013 writes it: whole seconds and nanoseconds since 1970 (UTC)."""

    seconds: int = Field(description="Seconds since 1970-01-01T00:00:00Z.")
    nanoSeconds: int = Field(ge=0, lt=1_000_000_000, description="Nanoseconds after those seconds.")


class TimeStampIn(RequestModel):
    """A deadline as MEC 013 writes times: seconds and nanoseconds since 1970 (UTC)."""

    seconds: int = Field(ge=0, le=10**10, description="Seconds since 1970-01-01T00:00:00Z.")
    nanoSeconds: int = Field(0, ge=0, lt=1_000_000_000, description="Nanoseconds after those seconds.")


class Velocity(MecModel):
    """Horizontal velocity (3GPP TS 23.032 'horizontal velocity', MEC 013 velocityType 1)."""

    velocityType: Literal[1] = Field(1, description="1 = HORIZONTAL: bearing and horizontal speed only.")
    bearing: int = Field(
        ge=0, le=359, description=f"Direction of travel, clockwise from true north. {DEGREES}."
    )
    horizontalSpeed: int = Field(
        ge=0, description="Speed over ground in km/h (as MEC 013 and TS 23.032 give it)."
    )


class LocationInfo(MecModel):
    """The vehicle's latest fix as a MEC 013 LocationInfo: a point with an uncertainty circle (shape 5)."""

    latitude: list[float] = Field(
        min_length=1, max_length=1, description=f"WGS-84 latitude of the fix (one point). {DEGREES}."
    )
    longitude: list[float] = Field(
        min_length=1, max_length=1, description=f"WGS-84 longitude of the fix, east positive. {DEGREES}."
    )
    altitude: float | None = Field(
        None,
        description="WGS-84 ellipsoidal height (m) of pipelines that estimate it (gnss_tight); absent otherwise.",
    )
    shape: Literal[5] = Field(
        5,
        description="5 = ELLIPSOID_POINT_UNCERT_CIRCLE: the point with an uncertainty circle of radius accuracy.",
    )
    accuracy: int = Field(
        ge=0,
        description="Radius (m, rounded up) of a circle about the point holding the true position with at least "
        "95% probability by the fix's own covariance (2.4477 standard deviations of its major axis).",
    )
    velocity: Velocity | None = Field(None, description="Absent when the fix has no velocity.")
    timestamp: TimeStamp = Field(description="When the server applied the batch that produced this fix.")


class UserInfo(MecModel):
    """One vehicle (a MEC 013 'user') and its latest fix."""

    address: str = Field(description="'acr:' followed by the vehicle id.")
    zoneId: str | None = Field(
        None, description="The first zone (by id) of the operator's zones (GET /v1/zones) holding the fix."
    )
    resourceURL: str = Field(description="This user's resource: the users query for its address.")
    timeStamp: TimeStamp = Field(description="When the server applied the batch of the latest fix.")
    locationInfo: LocationInfo | None = Field(
        None,
        description="Absent while the vehicle's filter has no usable position (uninitialised, or a diverged fix).",
    )


class UserList(MecModel):
    user: list[UserInfo] = Field(description="The vehicles with a live session, in vehicle id order.")
    resourceURL: str = Field(description="The query that produced this list.")


class InlineUserList(MecModel):
    userList: UserList


class TerminalDistance(MecModel):
    """The distance between two vehicles, or between a vehicle and a given point."""

    distance: int = Field(ge=0, description="Horizontal distance in whole metres (rounded).")
    accuracy: int = Field(
        ge=0,
        description="Uncertainty of distance (m, rounded up): the root sum of squares of the fixes' 95% radii.",
    )
    timestamp: TimeStamp = Field(description="When the server answered.")


class InlineTerminalDistance(MecModel):
    terminalDistance: TerminalDistance


class ZoneInfo(MecModel):
    """An operator zone as MEC 013 lists zones. Zones here are areas, not radio cells: no access points."""

    zoneId: str = Field(description="The zone's id (as in PUT /v1/zones/{zone_id}).")
    numberOfAccessPoints: int = Field(0, description="Always 0: the site's zones are areas, not radio cells.")
    numberOfUnserviceableAccessPoints: int = Field(0, description="Always 0, as numberOfAccessPoints.")
    numberOfUsers: int = Field(description="Vehicles whose latest fix is in the zone.")
    resourceURL: str = Field(description="This zone's resource.")


class ZoneList(MecModel):
    zone: list[ZoneInfo] = Field(description="Every operator zone, in id order.")
    resourceURL: str = Field(description="The query that produced this list.")


class InlineZoneList(MecModel):
    zoneList: ZoneList


class InlineZoneInfo(MecModel):
    zoneInfo: ZoneInfo


class LinkType(MecModel):
    href: str = Field(description="An absolute URL.")


class SelfLinks(MecModel):
    self_: LinkType = Field(alias="self")


class SubscriptionLink(MecModel):
    subscription: LinkType


_CALLBACK = (
    "Where notifications are POSTed: an http(s) URL on a host of EDGEPOS_CALLBACK_HOSTS (this machine only by "
    "default); anything else is 422."
)
_DEADLINE = "When the subscription ends by itself (server clock); a deadline already past is 422."


class UserLocationEventSubscriptionIn(RequestModel):
    """Notify when the vehicle enters or leaves any of the operator's zones."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "subscriptionType": "UserLocationEventSubscription",
                    "address": "acr:bus-42",
                    "callbackReference": "http://127.0.0.1:9000/notify",
                    "eventType": ["ENTERING_AREA_EVENT"],
                }
            ]
        }
    )

    subscriptionType: Literal["UserLocationEventSubscription"] = Field(
        description="Names the kind of subscription."
    )
    address: str = Field(pattern=ADDRESS_PATTERN, description="'acr:' followed by the vehicle id.")
    callbackReference: str = Field(max_length=2048, description=_CALLBACK)
    clientCorrelator: str | None = Field(None, max_length=256, description="Echoed back unchanged.")
    eventType: list[LocationEventType] | None = Field(
        None, min_length=1, description="Which crossings to notify; both when absent."
    )
    expiryDeadline: TimeStampIn | None = Field(None, description=_DEADLINE)


class UserLocationEventSubscription(MecModel):
    """A user location subscription as created (its _links.self is its URL)."""

    links: SelfLinks = Field(alias="_links")
    subscriptionType: Literal["UserLocationEventSubscription"] = Field(
        description="Names the kind of subscription."
    )
    address: str = Field(description="The vehicle watched: 'acr:' followed by its id.")
    callbackReference: str = Field(description="Where notifications are POSTed.")
    clientCorrelator: str | None = Field(None, description="As given.")
    eventType: list[LocationEventType] = Field(description="The crossings notified.")
    expiryDeadline: TimeStamp | None = Field(None, description="When it ends by itself, as given.")


class ZoneLocationEventSubscriptionIn(RequestModel):
    """Notify when vehicles enter or leave one of the operator's zones."""

    model_config = ConfigDict(
        json_schema_extra={
            "description": "Notify when vehicles enter or leave one of the operator's zones. The zone must "
            "exist (PUT /v1/zones/{zone_id}; the example's is the example zone 'depot'), else 404.",
            "examples": [
                {
                    "subscriptionType": "ZoneLocationEventSubscription",
                    "zoneId": "depot",
                    "callbackReference": "http://127.0.0.1:9000/notify",
                    "addressList": ["acr:bus-42"],
                }
            ],
        }
    )

    subscriptionType: Literal["ZoneLocationEventSubscription"] = Field(
        description="Names the kind of subscription."
    )
    zoneId: str = Field(
        pattern=ZONE_ID_PATTERN, description="An operator zone (GET /location/v3/queries/zones)."
    )
    callbackReference: str = Field(max_length=2048, description=_CALLBACK)
    clientCorrelator: str | None = Field(None, max_length=256, description="Echoed back unchanged.")
    addressList: list[Annotated[str, Field(pattern=ADDRESS_PATTERN)]] | None = Field(
        None,
        min_length=1,
        max_length=1000,
        description="Only these vehicles ('acr:' addresses); all when absent.",
    )
    locationEventType: list[LocationEventType] | None = Field(
        None, min_length=1, description="Which crossings to notify; both when absent."
    )
    expiryDeadline: TimeStampIn | None = Field(None, description=_DEADLINE)


class ZoneLocationEventSubscription(MecModel):
    """A zone location subscription as created (its _links.self is its URL)."""

    links: SelfLinks = Field(alias="_links")
    subscriptionType: Literal["ZoneLocationEventSubscription"] = Field(
        description="Names the kind of subscription."
    )
    zoneId: str = Field(description="The zone watched.")
    callbackReference: str = Field(description="Where notifications are POSTed.")
    clientCorrelator: str | None = Field(None, description="As given.")
    addressList: list[str] | None = Field(
        None, description="The vehicles watched, as given; absent: every vehicle."
    )
    locationEventType: list[LocationEventType] = Field(description="The crossings notified.")
    expiryDeadline: TimeStamp | None = Field(None, description="When it ends by itself, as given.")


class SubscriptionEntry(MecModel):
    href: str = Field(description="The subscription's URL.")
    subscriptionType: str = Field(
        description="UserLocationEventSubscription or ZoneLocationEventSubscription."
    )


class NotificationSubscriptionList(MecModel):
    links: SelfLinks = Field(alias="_links")
    subscription: list[SubscriptionEntry] = Field(description="The subscriptions, in id order.")


class UserLocationEventNotification(MecModel):
    """POSTed to a user subscription's callbackReference when its vehicle crosses a zone's boundary."""

    notificationType: Literal["UserLocationEventNotification"] = "UserLocationEventNotification"
    timeStamp: TimeStamp = Field(description="When the server noticed the crossing.")
    address: str
    eventType: LocationEventType
    zoneId: str
    locationInfo: LocationInfo | None = Field(None, description="The fix that showed the crossing.")
    links: SubscriptionLink = Field(alias="_links")


class ZoneLocationEventNotification(MecModel):
    """POSTed to a zone subscription's callbackReference when a vehicle enters or leaves its zone."""

    notificationType: Literal["ZoneLocationEventNotification"] = "ZoneLocationEventNotification"
    timeStamp: TimeStamp = Field(description="When the server noticed the crossing.")
    address: str
    zoneId: str
    userLocationEvent: LocationEventType
    links: SubscriptionLink = Field(alias="_links")


class ProblemDetails(MecModel):
    """RFC 7807 problem details (media type application/problem+json), as MEC 013 answers errors."""

    type: str = Field(description="A URI naming the kind of problem (about:blank: the status says it).")
    title: str = Field(description="The HTTP status's phrase.")
    status: int = Field(description="The HTTP status code.")
    detail: str = Field(description="What was wrong, naming each field and why.")
    instance: str = Field(description="The request's path.")


# -- /v1/zones: the operator's zones (SI units and radians, as every /v1 route) ---------------------
Point = Annotated[
    list[Annotated[float, Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]],
    Field(min_length=2, max_length=2),
]


class CircleIn(RequestModel):
    center: Point = Field(
        description="frame site: [x, y] (m, east and north of the site origin); frame wgs84: [latitude, "
        "longitude] (rad)."
    )
    radius: float = Field(gt=0, le=MAX_ZONE_RADIUS_M, description="Radius (m).")


class ZoneIn(RequestModel):
    """A zone: exactly one of circle and polygon, in the site frame or WGS-84."""

    model_config = ConfigDict(
        json_schema_extra={
            **exactly_one_of("circle", "polygon", json_type=("object", "array")),
            "examples": [{"frame": "site", "circle": {"center": [0.0, 0.0], "radius": 50.0}}],
        }
    )

    frame: Literal["site", "wgs84"] = Field(
        "site",
        description="site: points are [x, y] in metres (x east, y north of the origin); wgs84: [latitude, "
        "longitude] in radians (needs EDGEPOS_ORIGIN_LAT/LON; stored converted to the site frame).",
    )
    circle: CircleIn | None = Field(None, description="A disc; give it or polygon.")
    polygon: list[Point] | None = Field(
        None,
        min_length=3,
        max_length=MAX_POLYGON_VERTICES,
        description="Vertices of a simple polygon (edges must not cross, at least 3 distinct vertices "
        "enclosing an area, else 422), in either order; the last edge closes it.",
    )


class SiteShapeOut(ResponseModel):
    """The zone in the site frame (m), as vehicles' fixes are tested against it."""

    circle: CircleOut | None = Field(description="The circle in the site frame, or null.")
    polygon: list[list[float]] | None = Field(description="The polygon's vertices [x, y] (m), or null.")


class CircleOut(ResponseModel):
    center: list[float] = Field(
        description="[x, y] (m) in the site frame, or [latitude, longitude] (rad) in wgs84."
    )
    radius: float = Field(description="Radius (m).")


class ZoneOut(ResponseModel):
    """A zone as stored."""

    zone_id: str = Field(description="The zone's id.")
    frame: Literal["site", "wgs84"] = Field(description="The frame it was given in.")
    circle: CircleOut | None = Field(description="As given (frame's units).")
    polygon: list[list[float]] | None = Field(description="As given (frame's units).")
    site: SiteShapeOut
    updated_at: float = Field(description="When it was last written (Unix s, server clock).")


class ZoneListOut(ResponseModel):
    zones: list[ZoneOut] = Field(description="Every zone, in id order.")


SiteShapeOut.model_rebuild()
