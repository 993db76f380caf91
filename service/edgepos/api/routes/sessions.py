"""Vehicle sessions: open one (with the vehicle's credential or the admin key; the answer carries
the session's token), list them (admin), read one, delete it, and send it batches."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response, WebSocket

from edgepos.api import session_service
from edgepos.api.auth import (
    Principal,
    authorise_session_creation,
    bearer_scheme,
    require_admin,
    require_batch_session,
    require_session,
    require_vehicle,
)
from edgepos.api.batch_socket import BatchSocket
from edgepos.api.context import AppContext, Context, get_context
from edgepos.api.measurement_schemas import BatchIn
from edgepos.api.one_pass_body import OnePassBodyRoute, direct_route
from edgepos.api.routes import errors, json_body, known_query_parameters
from edgepos.api.schemas import (
    PIPELINE_NAME_PATTERN,
    VEHICLE_ID_PATTERN,
    BatchOut,
    SessionCreate,
    SessionCreated,
    SessionList,
    SessionOut,
    TrackOut,
)

router = APIRouter(prefix="/v1/sessions", tags=["sessions"], route_class=OnePassBodyRoute)
batch_router = APIRouter(prefix="/v1/sessions", tags=["sessions"])
"""The batch route alone: the app matches it before every other route (it takes nearly every request), and
documents it after :data:`router`'s."""

# OpenAPI links: how a client (and schemathesis' stateful tests) goes from one call to the next.
_READ, _SEND, _DELETE = (
    "get_session",
    "post_batch",
    "delete_session",
)


def _links(session_id: str, *targets: tuple[str, str, str]) -> dict[str, object]:
    return {
        name: {"operationId": operation, "parameters": {"session_id": session_id}, "description": text}
        for name, operation, text in targets
    }


_READ_IT = ("ReadSession", _READ, "Read this session (counters, last seq, latest fix).")
_SEND_TO_IT = ("SendBatch", _SEND, "Send this session a batch of measurements.")
_DELETE_IT = ("DeleteSession", _DELETE, "End this session.")
_FROM_BODY = "$response.body#/session_id"
_FROM_PATH = "$request.path.session_id"


@router.post(
    "",
    status_code=201,
    response_model=SessionCreated,
    summary="Open a session",
    responses={
        **errors(401, 403, 404, 413, 415, 422, 429, 503),
        201: {"links": _links(_FROM_BODY, _READ_IT, _SEND_TO_IT, _DELETE_IT)},
    },
)
async def create_session(
    request: Request,
    body: SessionCreate,
    context: Context,
    principal: Annotated[Principal, Depends(require_vehicle)],
    _json: Annotated[None, Depends(json_body)],
) -> SessionCreated:
    """Open a session for a vehicle, with that vehicle's credential (its key from POST /v1/vehicles, or a
    fleet-signed token with EDGEPOS_VEHICLE_AUTH=jwt) or the admin key (any vehicle). A vehicle has one
    live session: opening another supersedes the old one, whose token then gets 409 superseded.

    Keep the returned token: it is shown once and opens only this session (send it as
    ``Authorization: Bearer <token>``). Send the session batches with POST /v1/sessions/{session_id}/batches,
    or over one WebSocket, /v1/sessions/{session_id}/ws (protocol in docs/service.md, "Batches over a
    WebSocket")."""
    await authorise_session_creation(request, context, principal, body.vehicle_id)
    return await session_service.create_session(context, body, principal.vehicle_key_hash)


@router.get(
    "",
    response_model=SessionList,
    summary="List live sessions",
    dependencies=[
        Depends(require_admin),
        Depends(known_query_parameters("after", "limit", "pipeline", "vehicle_id")),
    ],
    responses=errors(401, 403, 422, 429, 503),
)
async def list_sessions(
    context: Context,
    after: Annotated[
        str | None,
        Query(
            max_length=64,
            description="Only sessions with ids after this one (the previous page's next_after).",
        ),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="Sessions per page.")] = 100,
    pipeline: Annotated[
        str | None, Query(pattern=PIPELINE_NAME_PATTERN, description="Only sessions of this pipeline.")
    ] = None,
    vehicle_id: Annotated[
        str | None, Query(pattern=VEHICLE_ID_PATTERN, description="Only this vehicle's session.")
    ] = None,
) -> SessionList:
    """Live sessions in session-id order, a page at a time, with their vehicle, pipeline, counters and
    the latest fix's time and status (admin key; a vehicle or session credential gets 403)."""
    return await session_service.list_sessions(context, after, limit, pipeline, vehicle_id)


@router.get(
    "/{session_id}",
    response_model=SessionOut,
    summary="Read a session",
    dependencies=[Depends(require_session)],
    responses={
        **errors(401, 403, 404, 409, 422, 429, 503),
        200: {"links": _links(_FROM_BODY, _SEND_TO_IT, _DELETE_IT)},
    },
)
async def get_session(session_id: str, context: Context) -> SessionOut:
    """Options, counters, model probabilities, last seq and the latest fix (session token or admin key)."""
    return await session_service.describe_session(context, session_id)


@router.get(
    "/{session_id}/track",
    response_model=TrackOut,
    summary="Read the session's recent track",
    dependencies=[Depends(require_session), Depends(known_query_parameters("smoothed"))],
    responses=errors(401, 403, 404, 409, 422, 429, 503),
)
async def get_track(
    session_id: str,
    context: Context,
    smoothed: Annotated[
        bool,
        Query(
            description="false: the filtered estimates; true: smoothed over the window (pipelines with a "
            "smoother: GET /v1/pipelines lists smoother true)."
        ),
    ] = False,
) -> TrackOut:
    """The estimates of the session's lag window (the last max_delay_s seconds), one per epoch, oldest
    first: filtered again from the window's start with the RSU registry and neighbour tracks as they are
    now, or with ``smoothed=true`` fixed-interval smoothed over the window, for mapping and analytics
    (session token or admin key). The state covariance is included (``state``)."""
    return await session_service.session_track(context, session_id, smoothed)


@router.delete(
    "/{session_id}",
    status_code=204,
    response_class=Response,
    summary="Delete a session",
    dependencies=[Depends(require_session)],
    responses=errors(401, 403, 404, 409, 422, 429, 503),
)
async def delete_session(session_id: str, context: Context) -> Response:
    """End the session and forget its state (session token or admin key)."""
    await session_service.delete_session(context, session_id)
    return Response(status_code=204)


async def post_batch(session_id: str, body: BatchIn, context: Context, request: Request) -> Response:
    """Filter the batch and return one fix per epoch (measurements sharing t), in time order.

    All or nothing: any problem gives 4xx listing every offending measurement and leaves the session
    unchanged. ``seq`` must be last_seq + 1; re-sending the last seq with the same content returns
    the stored response without applying it again; a different body for it, an older seq or a gap
    is 409.

    A vehicle that keeps a link open can send the same batches over one WebSocket instead,
    ``GET /v1/sessions/{session_id}/ws`` (same credential, seq rules, replay and error bodies; one frame per
    batch and per answer). WebSocket routes are not part of OpenAPI: the protocol is described in
    docs/service.md, section "Batches over a WebSocket"."""
    prefetched = getattr(request.state, "session_record", None)  # read by the token check
    body_bytes = await session_service.apply_batch(context, session_id, body, prefetched)
    return Response(body_bytes, media_type="application/json")


async def _post_batch_direct(request: Request, body: BatchIn) -> Response:
    """:func:`post_batch` with its dependencies called as FastAPI solves them (``one_pass_body.direct_route``):
    the context, the bearer credential, the session's check, the JSON content type, then the endpoint."""
    context = await get_context(request)
    credentials = await bearer_scheme(request)
    session_id: str = request.path_params["session_id"]
    await require_batch_session(request, session_id, context, credentials)
    await json_body(request)
    return await post_batch(session_id, body, context, request)


batch_router.add_api_route(
    "/{session_id}/batches",
    post_batch,
    methods=["POST"],
    response_model=BatchOut,
    summary="Send a batch of measurements",
    dependencies=[Depends(require_batch_session), Depends(json_body)],
    responses={
        **errors(401, 403, 404, 409, 413, 415, 422, 429, 503),
        200: {"links": _links(_FROM_PATH, _READ_IT, _SEND_TO_IT, _DELETE_IT)},
    },
    route_class_override=direct_route(
        _post_batch_direct, (get_context, bearer_scheme, require_batch_session, json_body, get_context)
    ),
)


@router.websocket("/{session_id}/ws")
async def batch_websocket(websocket: WebSocket, session_id: str) -> None:
    """Batches over one WebSocket (see :mod:`edgepos.api.batch_socket` and docs/service.md)."""
    context: AppContext = websocket.app.state.context
    await BatchSocket(websocket, context, session_id).serve()
