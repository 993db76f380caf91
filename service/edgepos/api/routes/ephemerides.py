"""The site's broadcast ephemerides: one RINEX 3 navigation file, shared by every session, worker and
replica through the store. Writes need the admin key; reads need any valid credential."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Depends, Request, Response

from edgepos.api.auth import require_admin, require_any
from edgepos.api.context import Context
from edgepos.api.ephemerides import NavigationFileError, decode_upload, parse, stored_document, summary
from edgepos.api.errors import ApiError
from edgepos.api.routes import errors
from edgepos.api.schemas import EphemeridesOut, ProblemModel

logger = logging.getLogger("edgepos.api")

PATH = "/v1/ephemerides"
router = APIRouter(prefix=PATH, tags=["ephemerides"])

_BODY = {
    "requestBody": {
        "required": True,
        "description": "A RINEX 3 navigation file (GPS, BeiDou and Galileo records are used; GLONASS and "
        "SBAS records are skipped), at most EDGEPOS_MAX_EPHEMERIDES_BYTES.",
        "content": {
            "text/plain": {"schema": {"type": "string"}},
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}


@router.put(
    "",
    response_model=EphemeridesOut,
    summary="Load the broadcast ephemerides (RINEX 3 navigation file)",
    dependencies=[Depends(require_admin)],
    responses=errors(401, 403, 413, 422, 503),
    openapi_extra=_BODY,
)
async def put_ephemerides(request: Request, context: Context) -> EphemeridesOut:
    """Replace the site's navigation file (admin key). The body is the file itself, sent as text/plain or
    application/octet-stream. It is parsed before it is stored: a malformed file is refused with the line
    and the reason, and the file loaded before stays. The answer summarises what was loaded."""
    body = await request.body()
    try:
        text = decode_upload(body)
        document = stored_document(text, context.store.clock())
        loaded = await context.run_filter(parse, document.text, document.digest, document.uploaded_at)
    except NavigationFileError as error:
        field = "body" if error.line is None else f"body.line[{error.line}]"
        where = "" if error.line is None else f" at line {error.line}"
        raise ApiError(
            "invalid_request",
            f"not a usable RINEX 3 navigation file{where}: {error.reason}; "
            "the loaded ephemerides are unchanged",
            [ProblemModel(index=None, field=field, reason=error.reason)],
        ) from None
    await context.store.put_ephemerides(document)
    context.ephemerides.remember(loaded)
    answer = summary(loaded)
    logger.info(
        "ephemerides loaded",
        extra={
            "event": "ephemerides_loaded",
            "digest": answer.digest,
            "satellites": answer.satellite_count,
            "bytes": answer.size_bytes,
        },
    )
    return answer


@router.get(
    "",
    response_model=EphemeridesOut,
    summary="Summary of the loaded ephemerides",
    dependencies=[Depends(require_any)],
    responses=errors(401, 404, 429, 503),
)
async def get_ephemerides(context: Context) -> EphemeridesOut:
    """Systems, satellites, validity window and ionosphere sets of the loaded file (admin key, any
    session token or a vehicle credential); 404 when none is loaded."""
    loaded = await context.ephemerides.current(context.store, context.run_filter)
    if loaded is None:
        raise ApiError("not_found", "no ephemerides are loaded (PUT /v1/ephemerides with the admin key)")
    return summary(loaded)


@router.delete(
    "",
    status_code=204,
    response_class=Response,
    summary="Unload the ephemerides",
    dependencies=[Depends(require_admin)],
    responses=errors(401, 403, 404, 503),
)
async def delete_ephemerides(context: Context) -> Response:
    """Remove the navigation file (admin key). Pseudoranges without sat_position and sat_clock are then
    refused until another is loaded."""
    if not await context.store.delete_ephemerides():
        raise ApiError("not_found", "no ephemerides are loaded")
    logger.info("ephemerides unloaded", extra={"event": "ephemerides_unloaded"})
    return Response(status_code=204)
