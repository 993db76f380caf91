"""The operator's zones (admin key): the areas of the MEC 013 adapter's zone queries and location events.

MEC 013 defines no way to write zones (the platform's operator defines them), so they live here, under
/v1 with its conventions (metres, radians, the /v1 error body). A zone is a circle or a simple polygon in
the site frame or in WGS-84; it is stored as given and converted to the site frame once.
"""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Depends, Path, Response

from edgepos.api.auth import require_admin
from edgepos.api.context import Context
from edgepos.api.errors import ApiError
from edgepos.api.location import subscriptions as subs
from edgepos.api.location import zones
from edgepos.api.location.schemas import ZONE_ID_PATTERN, ZoneIn, ZoneListOut, ZoneOut
from edgepos.api.routes import errors, json_body, known_query_parameters

router = APIRouter(prefix="/v1/zones", tags=["zones"], dependencies=[Depends(require_admin)])

ZoneId = Annotated[
    str, Path(pattern=ZONE_ID_PATTERN, description="Zone identifier (1-64 characters of A-Z a-z 0-9 . _ -).")
]


@router.put(
    "/{zone_id}",
    response_model=ZoneOut,
    summary="Define or replace a zone",
    dependencies=[Depends(json_body), Depends(known_query_parameters())],
    responses=errors(401, 403, 409, 413, 415, 422, 503),
)
async def put_zone(zone_id: ZoneId, body: ZoneIn, context: Context) -> ZoneOut:
    """Insert or replace the zone (admin key). A WGS-84 zone needs the site origin (409 without it).
    Vehicles already inside a replaced zone are not notified again; ones its new shape takes in or
    leaves out are, at the notifier's next look."""
    shape = zones.site_shape(body, context.origin)
    store = context.store
    existing = await store.list_documents(zones.KIND)
    if zone_id not in existing and len(existing) >= zones.MAX_ZONES:
        raise ApiError("conflict", f"the site already holds {zones.MAX_ZONES} zones; delete some first")
    text = zones.encode_zone(zone_id, body, shape, store.clock())
    await store.put_document(zones.KIND, zone_id, text)
    return zones.zone_out(text)


@router.get(
    "",
    response_model=ZoneListOut,
    summary="List the zones",
    dependencies=[Depends(known_query_parameters())],
    responses=errors(401, 403, 422, 503),
)
async def list_zones(context: Context) -> ZoneListOut:
    documents = await context.store.list_documents(zones.KIND)
    return ZoneListOut(zones=[zones.zone_out(text) for text in documents.values()])


@router.get(
    "/{zone_id}",
    response_model=ZoneOut,
    summary="One zone",
    dependencies=[Depends(known_query_parameters())],
    responses=errors(401, 403, 404, 422, 503),
)
async def get_zone(zone_id: ZoneId, context: Context) -> ZoneOut:
    text = await context.store.get_document(zones.KIND, zone_id)
    if text is None:
        raise ApiError("not_found", f"no zone {zone_id!r}")
    return zones.zone_out(text)


@router.delete(
    "/{zone_id}",
    status_code=204,
    summary="Delete a zone",
    dependencies=[Depends(known_query_parameters())],
    responses=errors(401, 403, 404, 409, 422, 503),
)
async def delete_zone(zone_id: ZoneId, context: Context) -> Response:
    """Delete the zone; 409 while zone subscriptions name it (delete them first, so that no subscriber
    is left waiting for events that can no longer come)."""
    store = context.store
    watching = [
        document["id"]
        for document in map(json.loads, (await store.list_documents(subs.KIND)).values())
        if document["kind"] == subs.ZONES and document["zone_id"] == zone_id
    ]
    if watching:
        raise ApiError(
            "conflict",
            f"zone {zone_id!r} has {len(watching)} zone subscription(s) ({', '.join(watching[:5])}); delete them "
            "first (DELETE /location/v3/subscriptions/zones/{subscriptionId})",
        )
    if not await store.delete_document(zones.KIND, zone_id):
        raise ApiError("not_found", f"no zone {zone_id!r}")
    return Response(status_code=204)
