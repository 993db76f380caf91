"""The site's RSU registry. Writes need the admin key; reads need any valid credential (the admin
key, a live session's token or a vehicle credential)."""

from __future__ import annotations

from collections import Counter
from typing import Annotated

from fastapi import APIRouter, Depends, Path, Response

from edgepos.api.auth import require_admin, require_any
from edgepos.api.context import Context
from edgepos.api.convert import rsu_from_wire, rsu_to_wire
from edgepos.api.errors import ApiError
from edgepos.api.routes import errors, json_body
from edgepos.api.schemas import (
    RSU_ID_PATTERN,
    ProblemModel,
    RsuBulk,
    RsuList,
    RsuModel,
    RsuOut,
    RsuPut,
    Upserted,
)

router = APIRouter(prefix="/v1/rsus", tags=["rsus"])

RsuId = Annotated[
    str,
    Path(pattern=RSU_ID_PATTERN, description="RSU identifier (1-64 characters of A-Z a-z 0-9 . _ : + -)."),
]


@router.put(
    "",
    response_model=Upserted,
    summary="Insert or replace many RSUs",
    dependencies=[Depends(require_admin), Depends(json_body)],
    responses=errors(401, 403, 413, 415, 422, 503),
)
async def put_rsus(body: RsuBulk, context: Context) -> Upserted:
    """Upsert every RSU of the body by id (admin key). Ids must be unique within one request."""
    counts = Counter(rsu.id for rsu in body.rsus)
    problems = [
        ProblemModel(index=None, field=f"rsus[{index}].id", reason=f"id {rsu.id!r} appears more than once")
        for index, rsu in enumerate(body.rsus)
        if counts[rsu.id] > 1
    ]
    if problems:
        raise ApiError("invalid_request", "RSU ids must be unique within one request", problems)
    upserted = await context.store.upsert_rsus(rsu_from_wire(rsu) for rsu in body.rsus)
    return Upserted(upserted=upserted)


@router.get(
    "",
    response_model=RsuList,
    summary="List every RSU",
    dependencies=[Depends(require_any)],
    responses=errors(401, 429, 503),
)
async def list_rsus(context: Context) -> RsuList:
    """Every registered RSU, sorted by id (admin key, any session token or a vehicle credential)."""
    return RsuList(rsus=[rsu_to_wire(rsu) for rsu in await context.store.list_rsus()])


@router.get(
    "/{rsu_id}",
    response_model=RsuOut,
    summary="Read one RSU",
    dependencies=[Depends(require_any)],
    responses=errors(401, 404, 422, 429, 503),
)
async def get_rsu(rsu_id: RsuId, context: Context) -> RsuOut:
    """One RSU by id (admin key, any session token or a vehicle credential)."""
    rsu = await context.store.get_rsu(rsu_id)
    if rsu is None:
        raise ApiError("not_found", f"no RSU {rsu_id!r}")
    return rsu_to_wire(rsu)


@router.put(
    "/{rsu_id}",
    response_model=RsuOut,
    summary="Insert or replace one RSU",
    dependencies=[Depends(require_admin), Depends(json_body)],
    responses=errors(401, 403, 413, 415, 422, 503),
)
async def put_rsu(body: RsuPut, rsu_id: RsuId, context: Context) -> RsuOut:
    """Upsert the RSU at this id (admin key); a body ``id``, if given, must equal the path's."""
    if body.id is not None and body.id != rsu_id:
        reason = f"must equal the path's rsu_id {rsu_id!r} or be left out"
        raise ApiError(
            "invalid_request",
            "the body's id does not match the path",
            [ProblemModel(index=None, field="id", reason=reason)],
        )
    rsu = RsuModel(id=rsu_id, **body.model_dump(exclude={"id"}))
    await context.store.upsert_rsus([rsu_from_wire(rsu)])
    return rsu_to_wire(rsu_from_wire(rsu))


@router.delete(
    "/{rsu_id}",
    status_code=204,
    response_class=Response,
    summary="Delete one RSU",
    dependencies=[Depends(require_admin)],
    responses=errors(401, 403, 404, 422, 503),
)
async def delete_rsu(rsu_id: RsuId, context: Context) -> Response:
    """Remove an RSU (admin key). Sessions that later report it get 'unknown RSU'."""
    if not await context.store.delete_rsu(rsu_id):
        raise ApiError("not_found", f"no RSU {rsu_id!r}")
    return Response(status_code=204)
