"""The fix stream: ``GET /v1/stream/fixes``, every applied fix as a server-sent event (see api.streams)."""

from __future__ import annotations

import re
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, Query
from fastapi.responses import StreamingResponse

from edgepos.api.auth import Principal, require_stream_reader
from edgepos.api.context import AppContext, Context
from edgepos.api.errors import ApiError
from edgepos.api.routes import errors, known_query_parameters
from edgepos.api.schemas import VEHICLE_ID_PATTERN, FixEventOut, ProblemModel, StreamEndOut, StreamMissedOut
from edgepos.api.streams import MAX_RATE_HZ, StreamFilter
from edgepos.store.fixlog import parse_event_id

PATH = "/v1/stream/fixes"
router = APIRouter(tags=["stream"])
_VEHICLE_ID = re.compile(VEHICLE_ID_PATTERN)


class EventStreamResponse(StreamingResponse):
    media_type = "text/event-stream"


_EVENTS = f"""A stream of server-sent events (`text/event-stream`), never ending by itself:

* `fix`, with `id:` (resume from it with the `Last-Event-ID` header) and data `FixEventOut`
  ({FixEventOut.__doc__.strip() if FixEventOut.__doc__ else ""});
* `missed`, without id, data `StreamMissedOut`: first, when resuming from an id the buffer no longer follows;
* `end`, without id, data `StreamEndOut`: the last event when the server ends the stream (a consumer too slow
  to keep up, or the session of the token ended);
* a comment `: ping` every EDGEPOS_STREAM_PING_S (15 s) while no fix comes, so proxies keep the connection.

The schema below is that of a `fix` event's data."""


def add_event_schemas(document: dict[str, Any]) -> None:
    """Put the data models of the ``missed`` and ``end`` events in the schema's components (the ``fix``
    event's is the route's response model)."""
    content = document["paths"][PATH]["get"]["responses"]["200"]["content"]["text/event-stream"]
    content["schema"] = {"$ref": "#/components/schemas/FixEventOut"}  # not a JSON string: one event's data
    schemas = document.setdefault("components", {}).setdefault("schemas", {})
    for model in (StreamMissedOut, StreamEndOut):
        schemas[model.__name__] = model.model_json_schema(
            mode="serialization", ref_template="#/components/schemas/{model}"
        )


def _invalid(field: str, reason: str) -> ApiError:
    return ApiError(
        "invalid_request",
        f"invalid {field}: {reason}",
        [ProblemModel(index=None, field=field, reason=reason)],
    )


def _values(raw: list[str] | None) -> list[str] | None:
    """A repeatable query parameter whose values may also be comma lists."""
    if not raw:
        return None
    return [value.strip() for item in raw for value in item.split(",") if value.strip()]


def _stream_filter(
    context: AppContext,
    principal: Principal,
    session_id: str | None,
    pipeline: list[str] | None,
    vehicle_id: list[str] | None,
) -> StreamFilter:
    if not principal.admin and not principal.reader:
        own = principal.session_id
        if own is None:
            raise ApiError(
                "forbidden",
                "a vehicle credential opens sessions only; read the fix stream with the session's token, the admin key or the read key",
            )
        if session_id is not None and session_id != own:
            raise ApiError(
                "forbidden",
                "a session token streams its own session's fixes only; every session's fixes need the admin key or the read key",
            )
        session_id = own
    pipelines = _values(pipeline)
    if pipelines is not None:
        unknown = sorted(set(pipelines) - set(context.pipelines))
        if unknown:
            known = ", ".join(sorted(context.pipelines))
            raise _invalid(
                "pipeline", f"unknown pipeline {', '.join(map(repr, unknown))}; available: {known}"
            )
    vehicles = _values(vehicle_id)
    if vehicles is not None:
        bad = [value for value in vehicles if not _VEHICLE_ID.match(value)]
        if bad:
            raise _invalid(
                "vehicle_id",
                f"{bad[0][:40]!r} is not a vehicle id (1-128 letters, digits, space and . _ : + @ / -)",
            )
    return StreamFilter(
        session_id=session_id,
        pipelines=None if pipelines is None else frozenset(pipelines),
        vehicles=None if vehicles is None else frozenset(vehicles),
    )


@router.get(
    PATH,
    response_class=EventStreamResponse,
    summary="Stream fixes as they are applied (server-sent events)",
    dependencies=[
        Depends(
            known_query_parameters("session_id", "pipeline", "vehicle_id", "max_rate_hz", "last_event_id")
        )
    ],
    responses={
        200: {"model": FixEventOut, "description": _EVENTS},
        **errors(401, 403, 422, 429, 503),
    },
)
async def stream_fixes(
    context: Context,
    principal: Annotated[Principal, Depends(require_stream_reader)],
    session_id: Annotated[
        str | None,
        Query(
            max_length=64,
            description="Only this session's fixes. A session token streams its own session's fixes without it; "
            "naming another session with a session token is 403.",
        ),
    ] = None,
    pipeline: Annotated[
        list[str] | None,
        Query(
            description="Only fixes of these pipelines (repeat the parameter or give a comma list); an unknown "
            "name is 422."
        ),
    ] = None,
    vehicle_id: Annotated[
        list[str] | None,
        Query(description="Only fixes of these vehicles (repeat the parameter or give a comma list)."),
    ] = None,
    max_rate_hz: Annotated[
        float | None,
        Query(
            gt=0,
            le=MAX_RATE_HZ,
            allow_inf_nan=False,
            description="At most this many fixes per second of each vehicle: a fix closer in time t than "
            "1/max_rate_hz to the vehicle's last fix sent is left out.",
        ),
    ] = None,
    last_event_id: Annotated[
        str | None,
        Query(
            max_length=40,
            description="Resume after this event id (as the Last-Event-ID header; the header wins).",
        ),
    ] = None,
    last_event_id_header: Annotated[
        str | None,
        Header(
            alias="Last-Event-ID",
            max_length=40,
            description="Resume after this event id: the fixes the stream's buffer still holds after it come first.",
        ),
    ] = None,
) -> EventStreamResponse:
    """Every applied fix as a server-sent event, as it is applied, from any worker or replica: with the admin
    key or the read key (EDGEPOS_READ_KEY) every session's (or those the filters keep), with a session token that session's only. Resume with
    ``Last-Event-ID``: the fixes after it that the buffer (EDGEPOS_STREAM_BUFFER) holds come first, after a
    ``missed`` event if it no longer holds them all. A consumer that falls EDGEPOS_STREAM_QUEUE fixes behind
    is ended with an ``end`` event: a slow consumer never delays the vehicles or other consumers."""
    stream_filter = _stream_filter(context, principal, session_id, pipeline, vehicle_id)
    resume = last_event_id_header if last_event_id_header is not None else last_event_id
    after = None
    if resume is not None and resume.strip():
        try:
            after = parse_event_id(resume)
        except ValueError as error:
            field = "Last-Event-ID" if last_event_id_header is not None else "last_event_id"
            raise _invalid(field, str(error)) from None
    hub = context.streams
    consumer, backlog, gap = await hub.subscribe(stream_filter, after)
    still_open = None
    if not principal.admin and stream_filter.session_id is not None:
        own = stream_filter.session_id

        async def session_open() -> bool:
            return await context.store.get(own) is not None

        still_open = session_open
    events = hub.events(consumer, backlog, gap, after, max_rate_hz, still_open)
    return EventStreamResponse(events, headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
