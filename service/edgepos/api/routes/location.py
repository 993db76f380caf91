"""The ETSI GS MEC 013 Location API adapter: ``/location/v3`` (read-only for positions).

Users are the vehicles with a live session (address ``acr:<vehicle id>``), located by their latest fix
(api.location.fixes); zones are the operator's (/v1/zones). Every route needs the admin key or the read
key (EDGEPOS_READ_KEY) and the site origin (EDGEPOS_ORIGIN_LAT/LON: 409 without it, since MEC 013 speaks
WGS-84 only). Errors are RFC 7807 problem details (api.location.problems).
"""

from __future__ import annotations

import json
import math
import re
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, Depends, Path, Query, Request, Response

from edgepos.api.auth import require_reader
from edgepos.api.context import AppContext, Context
from edgepos.api.errors import ApiError
from edgepos.api.location import subscriptions as subs
from edgepos.api.location.fixes import LatestFix, address_of, latest_fixes, timestamp, vehicle_of
from edgepos.api.location.problems import MEDIA_TYPE
from edgepos.api.location.schemas import (
    ADDRESS_PATTERN,
    LOCATION_EVENT_TYPES,
    ZONE_ID_PATTERN,
    InlineTerminalDistance,
    InlineUserList,
    InlineZoneInfo,
    InlineZoneList,
    LinkType,
    NotificationSubscriptionList,
    ProblemDetails,
    SelfLinks,
    SubscriptionEntry,
    TerminalDistance,
    TimeStampIn,
    UserInfo,
    UserList,
    UserLocationEventSubscription,
    UserLocationEventSubscriptionIn,
    ZoneInfo,
    ZoneList,
    ZoneLocationEventSubscription,
    ZoneLocationEventSubscriptionIn,
)
from edgepos.api.location.zones import load_zones, zones_holding
from edgepos.api.routes import json_body, known_query_parameters
from edgepos.api.schemas import ProblemModel
from edgepos.geo import GeodeticOrigin

PREFIX = "/location/v3"
_ADDRESS = re.compile(ADDRESS_PATTERN)
_SUBSCRIPTION_ID = r"^[0-9a-f]{24}$"
_PROBLEM_TEXT = {
    401: "Missing or invalid bearer credential.",
    403: "The credential is valid but is neither the admin key nor the read key.",
    404: "No such user, zone or subscription.",
    409: "The site origin is not configured (EDGEPOS_ORIGIN_LAT/LON), or the subscription limit is reached.",
    415: "The request body is not JSON.",
    422: "The request is invalid: detail names each field and why.",
    429: "Too many failed authentications; Retry-After says when to retry.",
    503: "The store does not answer; retry.",
}


def _problems(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for error statuses: problem details (see :func:`add_problem_schema`)."""
    content = {MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/ProblemDetails"}}}
    return {status: {"description": _PROBLEM_TEXT[status], "content": content} for status in statuses}


def add_problem_schema(document: dict[str, Any]) -> None:
    """Put ProblemDetails in the schema's components (the error responses above refer to it by name)."""
    schemas = document.setdefault("components", {}).setdefault("schemas", {})
    schemas["ProblemDetails"] = ProblemDetails.model_json_schema(
        mode="serialization", ref_template="#/components/schemas/{model}"
    )


async def site_origin(context: Context) -> GeodeticOrigin:
    """The site origin; 409 without one (MEC 013 positions are WGS-84, the fixes are in the site frame)."""
    if context.origin is None:
        raise ApiError(
            "conflict",
            "the MEC 013 location adapter needs the site origin to give WGS-84 positions: set EDGEPOS_ORIGIN_LAT "
            "and EDGEPOS_ORIGIN_LON (and EDGEPOS_ORIGIN_HEIGHT) and restart the service",
        )
    return context.origin


router = APIRouter(
    prefix=PREFIX,
    tags=["location (MEC 013)"],
    dependencies=[Depends(require_reader), Depends(site_origin)],
)
Origin = Annotated[GeodeticOrigin, Depends(site_origin)]


def _invalid(field: str, reason: str) -> ApiError:
    return ApiError(
        "invalid_request",
        f"invalid {field}: {reason}",
        [ProblemModel(index=None, field=field, reason=reason)],
    )


def _values(raw: list[str] | None) -> list[str]:
    """A repeatable query parameter whose values may also be comma lists (ids never hold commas)."""
    return [value.strip() for item in raw or [] for value in item.split(",") if value.strip()]


def _vehicles(addresses: list[str]) -> list[str]:
    for address in addresses:
        if not _ADDRESS.match(address):
            raise _invalid("address", f"{address[:60]!r} is not 'acr:' followed by a vehicle id")
    return [vehicle_of(address) for address in addresses]


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/") + PREFIX


def _user_url(request: Request, vehicle_id: str) -> str:
    return f"{_base(request)}/queries/users?address={quote(address_of(vehicle_id), safe=':')}"


def _user(request: Request, latest: LatestFix, zones: dict[str, Any], origin: GeodeticOrigin) -> UserInfo:
    usable = latest.usable
    inside = zones_holding(zones, *latest.xy) if usable else []
    return UserInfo(
        address=address_of(latest.vehicle_id),
        zoneId=inside[0] if inside else None,
        resourceURL=_user_url(request, latest.vehicle_id),
        timeStamp=timestamp(latest.at),
        locationInfo=latest.location_info(origin) if usable else None,
    )


AddressQuery = Annotated[
    list[str] | None,
    Query(
        description="'acr:' followed by a vehicle id; repeat the parameter (or give a comma list) for several."
    ),
]


@router.get(
    "/queries/users",
    response_model=InlineUserList,
    response_model_exclude_none=True,
    summary="The vehicles' latest locations (MEC 013 UE location lookup)",
    dependencies=[Depends(known_query_parameters("address", "zoneId"))],
    responses=_problems(401, 403, 404, 409, 422, 429, 503),
)
async def query_users(
    request: Request,
    context: Context,
    origin: Origin,
    address: AddressQuery = None,
    zoneId: Annotated[
        list[str] | None, Query(description="Only vehicles whose latest fix is in one of these zones.")
    ] = None,
) -> InlineUserList:
    """Every vehicle with a live session and a fix, or those named by ``address``, or those in ``zoneId``'s
    zones. An address of a vehicle without a live session is left out; 404 when none of them has one.
    An unknown zoneId is 422."""
    addresses = _values(address)
    vehicles = _vehicles(addresses) if addresses else None
    zones = await load_zones(context.store)
    wanted_zones = _values(zoneId)
    unknown = [zone for zone in wanted_zones if zone not in zones]
    if unknown:
        raise _invalid("zoneId", f"unknown zone {unknown[0][:64]!r}; see GET {PREFIX}/queries/zones")
    fixes = await latest_fixes(context.store, vehicles)
    if vehicles is not None and not fixes:
        raise ApiError("not_found", f"no vehicle of {', '.join(addresses[:5])} has a live session with a fix")
    users = [_user(request, latest, zones, origin) for latest in fixes.values()]
    if wanted_zones:
        chosen = {zone: zones[zone] for zone in wanted_zones}
        users = [
            user
            for user, latest in zip(users, fixes.values(), strict=True)
            if latest.usable and zones_holding(chosen, *latest.xy)
        ]
    return InlineUserList(userList=UserList(user=users, resourceURL=str(request.url)))


@router.get(
    "/queries/distance",
    response_model=InlineTerminalDistance,
    summary="Distance between two vehicles, or a vehicle and a point (MEC 013 distance lookup)",
    dependencies=[Depends(known_query_parameters("address", "latitude", "longitude"))],
    responses=_problems(401, 403, 404, 409, 422, 429, 503),
)
async def query_distance(
    context: Context,
    origin: Origin,
    address: AddressQuery = None,
    latitude: Annotated[
        float | None,
        Query(
            ge=-90,
            le=90,
            allow_inf_nan=False,
            description="The point's WGS-84 latitude, with one address. Degrees.",
        ),
    ] = None,
    longitude: Annotated[
        float | None,
        Query(
            ge=-180,
            le=180,
            allow_inf_nan=False,
            description="The point's WGS-84 longitude, with one address. Degrees.",
        ),
    ] = None,
) -> InlineTerminalDistance:
    """Two addresses: the distance between the two vehicles' latest fixes; one address with latitude and
    longitude: from the vehicle to that point (at the origin's height). In the site's plane, whole metres."""
    addresses = _values(address)
    vehicles = _vehicles(addresses)
    point = latitude is not None or longitude is not None
    if point and (latitude is None or longitude is None):
        raise _invalid(
            "latitude" if latitude is None else "longitude", "give latitude and longitude together"
        )
    if len(vehicles) != (1 if point else 2):
        reason = (
            "give one address with latitude and longitude"
            if point
            else "give two addresses, or one with latitude and longitude"
        )
        raise _invalid("address", reason)
    fixes = await latest_fixes(context.store, vehicles)
    for vehicle_id in vehicles:
        if vehicle_id not in fixes or not fixes[vehicle_id].usable:
            raise ApiError("not_found", f"{address_of(vehicle_id)!r} has no live session with a usable fix")
    first = fixes[vehicles[0]]
    if point:
        assert latitude is not None and longitude is not None
        east, north, _ = origin.geodetic_to_enu(math.radians(latitude), math.radians(longitude))
        other, other_accuracy = (east, north), 0.0
    else:
        second = fixes[vehicles[1]]
        other, other_accuracy = second.xy, second.accuracy_m()
    distance = math.hypot(first.xy[0] - other[0], first.xy[1] - other[1])
    accuracy = math.hypot(first.accuracy_m(), other_accuracy)
    return InlineTerminalDistance(
        terminalDistance=TerminalDistance(
            distance=round(distance), accuracy=math.ceil(accuracy), timestamp=timestamp(context.store.clock())
        )
    )


async def _zone_infos(request: Request, context: AppContext) -> list[ZoneInfo]:
    zones = await load_zones(context.store)
    counts = dict.fromkeys(zones, 0)
    if zones:
        for latest in (await latest_fixes(context.store)).values():
            if latest.usable:
                for zone_id in zones_holding(zones, *latest.xy):
                    counts[zone_id] += 1
    return [
        ZoneInfo(zoneId=zone_id, numberOfUsers=count, resourceURL=f"{_base(request)}/queries/zones/{zone_id}")
        for zone_id, count in counts.items()
    ]


@router.get(
    "/queries/zones",
    response_model=InlineZoneList,
    summary="The operator's zones and how many vehicles are in each (MEC 013 zone lookup)",
    dependencies=[Depends(known_query_parameters())],
    responses=_problems(401, 403, 409, 422, 429, 503),
)
async def query_zones(request: Request, context: Context) -> InlineZoneList:
    """The zones defined with PUT /v1/zones/{zone_id}."""
    infos = await _zone_infos(request, context)
    return InlineZoneList(zoneList=ZoneList(zone=infos, resourceURL=str(request.url)))


@router.get(
    "/queries/zones/{zoneId}",
    response_model=InlineZoneInfo,
    summary="One operator zone",
    dependencies=[Depends(known_query_parameters())],
    responses=_problems(401, 403, 404, 409, 422, 429, 503),
)
async def query_zone(
    request: Request,
    context: Context,
    zoneId: Annotated[str, Path(pattern=ZONE_ID_PATTERN, description="An operator zone's id.")],
) -> InlineZoneInfo:
    for info in await _zone_infos(request, context):
        if info.zoneId == zoneId:
            return InlineZoneInfo(zoneInfo=info)
    raise ApiError("not_found", f"no zone {zoneId!r}")


# -- subscriptions ---------------------------------------------------------------------------------
def _deadline(deadline: TimeStampIn | None, now: float) -> float | None:
    if deadline is None:
        return None
    at = deadline.seconds + deadline.nanoSeconds / 1e9
    if at <= now:
        raise _invalid("expiryDeadline", "is already past")
    return at


async def _create(
    request: Request,
    context: AppContext,
    kind: str,
    wire: dict[str, Any],
    **fields: Any,
) -> tuple[str, dict[str, Any]]:
    """Store a new subscription whose memberships start from the fixes as they are now (so only later
    crossings are notified); returns its id and its wire form with _links."""
    store = context.store
    if len(await store.list_documents(subs.KIND)) >= subs.MAX_SUBSCRIPTIONS:
        raise ApiError(
            "conflict",
            f"the site already holds {subs.MAX_SUBSCRIPTIONS} location subscriptions; delete some first",
        )
    subscription_id = subs.new_subscription_id()
    href = f"{_base(request)}/subscriptions/{kind}/{subscription_id}"
    wire = {"_links": {"self": {"href": href}}, **wire}
    now = store.clock()
    document = subs.new_document(kind, subscription_id, wire, href, members={}, now=now, **fields)
    vehicles = subs.watched_vehicles(document)
    zones = await load_zones(store)
    document["members"] = subs.memberships(document, zones, await latest_fixes(store, vehicles))
    await store.put_document(subs.KIND, subscription_id, subs.encode(document))
    return href, wire


def _created(href: str, wire: dict[str, Any]) -> Response:
    return Response(
        json.dumps(wire), status_code=201, media_type="application/json", headers={"Location": href}
    )


@router.post(
    "/subscriptions/users",
    response_model=UserLocationEventSubscription,
    status_code=201,
    summary="Subscribe to a vehicle entering or leaving the operator's zones",
    dependencies=[Depends(json_body), Depends(known_query_parameters())],
    responses=_problems(401, 403, 409, 415, 422, 429, 503),
)
async def subscribe_user(
    request: Request, context: Context, body: UserLocationEventSubscriptionIn
) -> Response:
    """Creates a UserLocationEventSubscription: a UserLocationEventNotification is POSTed to
    callbackReference each time the vehicle's latest fix enters or leaves a zone (checked every
    EDGEPOS_LOCATION_POLL_S). The answer carries Location: the subscription's URL."""
    subs.check_callback(body.callbackReference, context.settings.callback_host_set)
    events = list(body.eventType or LOCATION_EVENT_TYPES)
    expires_at = _deadline(body.expiryDeadline, context.store.clock())
    out = UserLocationEventSubscription.model_validate(
        {**body.model_dump(exclude_none=True), "eventType": events, "_links": {"self": {"href": "-"}}}
    )
    wire = out.model_dump(mode="json", exclude_none=True, exclude={"links"})
    href, wire = await _create(
        request,
        context,
        subs.USERS,
        wire,
        address=vehicle_of(body.address),
        zone_id=None,
        vehicles=None,
        events=events,
        expires_at=expires_at,
    )
    return _created(href, wire)


@router.post(
    "/subscriptions/zones",
    response_model=ZoneLocationEventSubscription,
    status_code=201,
    summary="Subscribe to vehicles entering or leaving an operator zone",
    dependencies=[Depends(json_body), Depends(known_query_parameters())],
    responses=_problems(401, 403, 409, 415, 422, 429, 503),
)
async def subscribe_zone(
    request: Request, context: Context, body: ZoneLocationEventSubscriptionIn
) -> Response:
    """Creates a ZoneLocationEventSubscription: a ZoneLocationEventNotification is POSTed to
    callbackReference each time a vehicle (of addressList, or any) enters or leaves the zone. An unknown
    zoneId is 422."""
    subs.check_callback(body.callbackReference, context.settings.callback_host_set)
    if await context.store.get_document("zones", body.zoneId) is None:
        raise _invalid("zoneId", f"unknown zone {body.zoneId!r}; see GET {PREFIX}/queries/zones")
    events = list(body.locationEventType or LOCATION_EVENT_TYPES)
    expires_at = _deadline(body.expiryDeadline, context.store.clock())
    out = ZoneLocationEventSubscription.model_validate(
        {**body.model_dump(exclude_none=True), "locationEventType": events, "_links": {"self": {"href": "-"}}}
    )
    wire = out.model_dump(mode="json", exclude_none=True, exclude={"links"})
    vehicles = None if body.addressList is None else sorted({vehicle_of(a) for a in body.addressList})
    href, wire = await _create(
        request,
        context,
        subs.ZONES,
        wire,
        address=None,
        zone_id=body.zoneId,
        vehicles=vehicles,
        events=events,
        expires_at=expires_at,
    )
    return _created(href, wire)


SubscriptionType = Annotated[
    str | None,
    Query(description="'event' (the only kind this adapter offers) or 'periodic' (always an empty list)."),
]


async def _list(
    request: Request, context: AppContext, kind: str, subscription_type: str | None, keep: Any
) -> NotificationSubscriptionList:
    if subscription_type is not None and subscription_type not in ("event", "periodic"):
        raise _invalid("subscription_type", f"{subscription_type[:40]!r} is not one of 'event', 'periodic'")
    entries = []
    if subscription_type != "periodic":
        for text in (await context.store.list_documents(subs.KIND)).values():
            document = json.loads(text)
            if document["kind"] == kind and keep(document):
                entries.append(
                    SubscriptionEntry(
                        href=document["href"], subscriptionType=document["subscription"]["subscriptionType"]
                    )
                )
    return NotificationSubscriptionList(
        links=SelfLinks(self_=LinkType(href=str(request.url))), subscription=entries
    )


@router.get(
    "/subscriptions/users",
    response_model=NotificationSubscriptionList,
    summary="The user location subscriptions",
    dependencies=[Depends(known_query_parameters("subscription_type", "address"))],
    responses=_problems(401, 403, 409, 422, 429, 503),
)
async def list_user_subscriptions(
    request: Request,
    context: Context,
    subscription_type: SubscriptionType = None,
    address: Annotated[
        str | None, Query(description="Only the subscriptions of this 'acr:' address.")
    ] = None,
) -> NotificationSubscriptionList:
    vehicle = None if address is None else _vehicles([address])[0]
    return await _list(
        request, context, subs.USERS, subscription_type, lambda d: vehicle is None or d["address"] == vehicle
    )


@router.get(
    "/subscriptions/zones",
    response_model=NotificationSubscriptionList,
    summary="The zone location subscriptions",
    dependencies=[Depends(known_query_parameters("subscription_type", "zoneId"))],
    responses=_problems(401, 403, 409, 422, 429, 503),
)
async def list_zone_subscriptions(
    request: Request,
    context: Context,
    subscription_type: SubscriptionType = None,
    zoneId: Annotated[
        str | None, Query(pattern=ZONE_ID_PATTERN, description="Only the subscriptions of this zone.")
    ] = None,
) -> NotificationSubscriptionList:
    return await _list(
        request, context, subs.ZONES, subscription_type, lambda d: zoneId is None or d["zone_id"] == zoneId
    )


SubscriptionId = Annotated[
    str, Path(pattern=_SUBSCRIPTION_ID, description="From the subscription's Location.")
]


async def _document(context: AppContext, kind: str, subscription_id: str) -> dict[str, Any]:
    text = await context.store.get_document(subs.KIND, subscription_id)
    document: dict[str, Any] | None = None if text is None else json.loads(text)
    if document is None or document["kind"] != kind:
        raise ApiError(
            "not_found", f"no {kind} subscription {subscription_id!r} (deleted, expired, or never made)"
        )
    return document


@router.get(
    "/subscriptions/users/{subscriptionId}",
    response_model=UserLocationEventSubscription,
    response_model_exclude_none=True,
    summary="One user location subscription",
    dependencies=[Depends(known_query_parameters())],
    responses=_problems(401, 403, 404, 409, 422, 429, 503),
)
async def get_user_subscription(context: Context, subscriptionId: SubscriptionId) -> Any:
    return (await _document(context, subs.USERS, subscriptionId))["subscription"]


@router.get(
    "/subscriptions/zones/{subscriptionId}",
    response_model=ZoneLocationEventSubscription,
    response_model_exclude_none=True,
    summary="One zone location subscription",
    dependencies=[Depends(known_query_parameters())],
    responses=_problems(401, 403, 404, 409, 422, 429, 503),
)
async def get_zone_subscription(context: Context, subscriptionId: SubscriptionId) -> Any:
    return (await _document(context, subs.ZONES, subscriptionId))["subscription"]


async def _delete(context: AppContext, kind: str, subscription_id: str) -> Response:
    await _document(context, kind, subscription_id)
    if not await context.store.delete_document(subs.KIND, subscription_id):
        raise ApiError("not_found", f"no {kind} subscription {subscription_id!r}")
    return Response(status_code=204)


@router.delete(
    "/subscriptions/users/{subscriptionId}",
    status_code=204,
    summary="End a user location subscription",
    dependencies=[Depends(known_query_parameters())],
    responses=_problems(401, 403, 404, 409, 422, 429, 503),
)
async def delete_user_subscription(context: Context, subscriptionId: SubscriptionId) -> Response:
    return await _delete(context, subs.USERS, subscriptionId)


@router.delete(
    "/subscriptions/zones/{subscriptionId}",
    status_code=204,
    summary="End a zone location subscription",
    dependencies=[Depends(known_query_parameters())],
    responses=_problems(401, 403, 404, 409, 422, 429, 503),
)
async def delete_zone_subscription(context: Context, subscriptionId: SubscriptionId) -> Response:
    return await _delete(context, subs.ZONES, subscriptionId)
