"""HTTP routes of API v1; each module exposes ``router``."""

from __future__ import annotations

import email.message
from collections.abc import Awaitable, Callable
from typing import Any

from fastapi import Request

from edgepos.api.errors import ApiError
from edgepos.api.schemas import ErrorBody, ProblemModel

_DESCRIPTIONS = {
    401: "Missing or invalid bearer credential.",
    403: "The credential is valid but does not open this resource.",
    404: "No such resource.",
    409: "A conflict: the batch's seq does not follow the session's last applied seq, the vehicle is "
    "already registered, or (code superseded) a newer session of the same vehicle replaced this one.",
    415: "The request body is not JSON: send 'Content-Type: application/json' (UTF-8).",
    413: "The request body is larger than EDGEPOS_MAX_BODY_BYTES (EDGEPOS_MAX_EPHEMERIDES_BYTES for a "
    "navigation file).",
    422: "The request is invalid; every problem is listed.",
    429: "Too many sessions (EDGEPOS_MAX_SESSIONS), the session token over its request rate "
    "(EDGEPOS_RATE_LIMIT_PER_S), too many failed authentications from this address or with this credential "
    "(EDGEPOS_AUTH_FAILURE_RATE_PER_S), or sessions opened too fast (EDGEPOS_SESSION_CREATE_RATE_PER_S); "
    "Retry-After says when to retry.",
    503: "Temporarily unavailable (e.g. the session store does not answer); retry.",
}


def errors(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for error statuses, all with the standard error body."""
    return {status: {"model": ErrorBody, "description": _DESCRIPTIONS[status]} for status in statuses}


def known_query_parameters(*names: str) -> Callable[[Request], Awaitable[None]]:
    """A dependency refusing query parameters other than ``names`` (422 naming each): a misspelt
    filter such as ``?pipline=gnss_tight`` would otherwise be ignored and answer everything."""
    allowed = frozenset(names)

    async def check(request: Request) -> None:  # a coroutine: FastAPI runs a plain function in its threadpool
        unknown = sorted({name for name in request.query_params if name not in allowed})
        if unknown:
            known = ", ".join(sorted(allowed))
            raise ApiError(
                "invalid_request",
                f"unknown query parameter{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}",
                [
                    ProblemModel(index=None, field=name, reason=f"unknown query parameter; known: {known}")
                    for name in unknown
                ],
            )

    return check


async def json_body(request: Request) -> None:
    """A dependency (a coroutine although it never awaits: FastAPI would run a plain function in its
    threadpool, a thread hop and an interpreter-lock hand-off per request) refusing a request body that is not declared JSON (415): a text/plain, form-encoded
    or UTF-16 body is not read as JSON by guesswork. ``application/json`` and ``application/*+json``
    in UTF-8 (no charset, or charset=utf-8) pass."""
    declared = request.headers.get("content-type")
    if declared == "application/json":  # what every client sends: no parsing
        return
    message = email.message.Message()
    message["content-type"] = declared or ""
    subtype = message.get_content_subtype()
    charset = (message.get_param("charset") or "utf-8") if declared else "utf-8"
    json_type = message.get_content_maintype() == "application" and (
        subtype == "json" or subtype.endswith("+json")
    )
    if declared and json_type and str(charset).lower() in ("utf-8", "utf8"):
        return
    what = f"Content-Type {declared!r}" if declared else "no Content-Type"
    raise ApiError(
        "unsupported_media_type",
        f"the request body must be JSON in UTF-8 with 'Content-Type: application/json'; it came with {what}",
        [ProblemModel(index=None, field="Content-Type", reason="must be application/json (UTF-8)")],
    )
