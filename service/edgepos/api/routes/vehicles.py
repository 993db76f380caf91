"""The vehicle registry (admin key): who may open sessions for which vehicle id.

A registered vehicle gets a key, shown once and stored only as its SHA-256; with
EDGEPOS_VEHICLE_AUTH=key (the default) that key opens sessions for that vehicle only. Revoking a
vehicle removes its key and ends its live session at once; rotating issues a new key and makes the
old one open nothing. Vehicle ids may contain '/', so the id is the rest of the path.
"""

from __future__ import annotations

import logging
from typing import Annotated

from fastapi import APIRouter, Depends, Path, Query

from edgepos.api.auth import hash_token, new_vehicle_key, require_admin
from edgepos.api.context import AppContext, Context
from edgepos.api.errors import ApiError
from edgepos.api.routes import errors, json_body, known_query_parameters
from edgepos.api.schemas import VEHICLE_ID_PATTERN, ProblemModel
from edgepos.api.vehicle_schemas import (
    VehicleCreate,
    VehicleImport,
    VehicleImported,
    VehicleKeyIssued,
    VehicleList,
    VehicleOut,
    VehicleRevoked,
)
from edgepos.store.base import VehicleRecord

logger = logging.getLogger("edgepos.api")

router = APIRouter(prefix="/v1/vehicles", tags=["vehicles"], dependencies=[Depends(require_admin)])

VehicleId = Annotated[
    str,
    Path(
        pattern=VEHICLE_ID_PATTERN,
        description="The vehicle's identifier (1-128 characters of letters, digits, space and . _ : + @ / -; "
        "percent-encode the space).",
    ),
]


def _issue(context: AppContext, vehicle_id: str) -> tuple[VehicleRecord, str]:
    key = new_vehicle_key()
    now = context.store.clock()
    return VehicleRecord(vehicle_id, hash_token(key), now, now), key


def _issued(record: VehicleRecord, key: str) -> VehicleKeyIssued:
    return VehicleKeyIssued(
        vehicle_id=record.vehicle_id,
        created_at=record.created_at,
        key_issued_at=record.key_issued_at,
        key=key,
    )


def _out(record: VehicleRecord) -> VehicleOut:
    return VehicleOut(
        vehicle_id=record.vehicle_id, created_at=record.created_at, key_issued_at=record.key_issued_at
    )


def _not_registered(vehicle_id: str) -> ApiError:
    return ApiError("not_found", f"vehicle {vehicle_id!r} is not registered")


@router.post(
    "",
    status_code=201,
    response_model=VehicleKeyIssued,
    summary="Register a vehicle",
    dependencies=[Depends(json_body)],
    responses=errors(401, 403, 409, 413, 415, 422, 429, 503),
)
async def register_vehicle(body: VehicleCreate, context: Context) -> VehicleKeyIssued:
    """Register a vehicle and issue its key (shown once: hand it to the vehicle). A vehicle already
    registered is 409: rotate its key with POST /v1/vehicles/{vehicle_id}/key instead."""
    record, key = _issue(context, body.vehicle_id)
    if not await context.store.add_vehicles([record]):
        reason = "already registered; POST /v1/vehicles/{vehicle_id}/key issues it a new key"
        raise ApiError(
            "conflict",
            f"vehicle {body.vehicle_id!r} is {reason}",
            [ProblemModel(index=None, field="vehicle_id", reason=reason)],
        )
    logger.info("vehicle registered", extra={"event": "vehicle_registered", "vehicle_id": body.vehicle_id})
    return _issued(record, key)


@router.post(
    "/bulk",
    response_model=VehicleImported,
    summary="Register many vehicles",
    dependencies=[Depends(json_body)],
    responses=errors(401, 403, 413, 415, 422, 429, 503),
)
async def import_vehicles(body: VehicleImport, context: Context) -> VehicleImported:
    """Register up to 5,000 vehicles in one atomic write (``edgepos vehicles import`` sends a CSV in such
    chunks). Ids already registered are listed and left as they are; the others get keys, shown once."""
    issued = {vehicle.vehicle_id: _issue(context, vehicle.vehicle_id) for vehicle in body.vehicles}
    added = set(await context.store.add_vehicles([record for record, _ in issued.values()]))
    logger.info("vehicles imported", extra={"event": "vehicles_imported", "count": len(added)})
    return VehicleImported(
        registered=[_issued(*issued[vid]) for vid in issued if vid in added],
        already_registered=[vid for vid in issued if vid not in added],
    )


@router.get(
    "",
    response_model=VehicleList,
    summary="List registered vehicles",
    dependencies=[Depends(known_query_parameters("after", "limit"))],
    responses=errors(401, 403, 422, 429, 503),
)
async def list_vehicles(
    context: Context,
    after: Annotated[
        str | None,
        Query(
            max_length=128,
            description="Only vehicles with ids after this one (the previous page's next_after).",
        ),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="Vehicles per page.")] = 100,
) -> VehicleList:
    """Registered vehicles in id order, a page at a time (never a key)."""
    page = await context.store.list_vehicles(after=after, limit=limit + 1)
    more = len(page) > limit
    page = page[:limit]
    return VehicleList(
        vehicles=[_out(record) for record in page],
        total=await context.store.count_vehicles(),
        next_after=page[-1].vehicle_id if more else None,
    )


@router.post(
    "/{vehicle_id:path}/key",
    response_model=VehicleKeyIssued,
    summary="Rotate a vehicle's key",
    responses=errors(401, 403, 404, 422, 429, 503),
)
async def rotate_vehicle_key(vehicle_id: VehicleId, context: Context) -> VehicleKeyIssued:
    """Issue the vehicle a new key (shown once); the old key opens nothing from now on. Its live
    session keeps running: a session is opened by the key but spoken to with its own token."""
    key = new_vehicle_key()
    record = await context.store.rotate_vehicle_key(vehicle_id, hash_token(key), context.store.clock())
    if record is None:
        raise _not_registered(vehicle_id)
    logger.info("vehicle key rotated", extra={"event": "vehicle_key_rotated", "vehicle_id": vehicle_id})
    return _issued(record, key)


@router.get(
    "/{vehicle_id:path}",
    response_model=VehicleOut,
    summary="Read a registered vehicle",
    responses=errors(401, 403, 404, 422, 429, 503),
)
async def get_vehicle(vehicle_id: VehicleId, context: Context) -> VehicleOut:
    record = await context.store.get_vehicle(vehicle_id)
    if record is None:
        raise _not_registered(vehicle_id)
    return _out(record)


@router.delete(
    "/{vehicle_id:path}",
    response_model=VehicleRevoked,
    summary="Revoke a vehicle",
    responses=errors(401, 403, 404, 422, 429, 503),
)
async def revoke_vehicle(vehicle_id: VehicleId, context: Context) -> VehicleRevoked:
    """Remove the vehicle from the registry: its key opens nothing, its live session ends (its token
    gets 404) and its published track is withdrawn, in one atomic step."""
    revocation = await context.store.delete_vehicle(vehicle_id)
    if revocation is None:
        raise _not_registered(vehicle_id)
    context.metrics.vehicles_revoked.inc()
    logger.info(
        "vehicle revoked",
        extra={"event": "vehicle_revoked", "vehicle_id": vehicle_id, "session_id": revocation.ended_session},
    )
    return VehicleRevoked(vehicle_id=revocation.vehicle_id, ended_session=revocation.ended_session)
