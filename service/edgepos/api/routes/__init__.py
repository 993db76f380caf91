"""HTTP routes of API v1; each module exposes ``router``."""

from __future__ import annotations

from typing import Any

from edgepos.api.schemas import ErrorBody

_DESCRIPTIONS = {
    401: "Missing or invalid bearer credential.",
    403: "The credential is valid but does not open this resource.",
    404: "No such resource.",
    409: "The batch's seq does not follow the session's last applied seq.",
    413: "The request body is larger than EDGEPOS_MAX_BODY_BYTES (EDGEPOS_MAX_EPHEMERIDES_BYTES for a "
    "navigation file).",
    422: "The request is invalid; every problem is listed.",
    429: "Too many sessions (EDGEPOS_MAX_SESSIONS), or the session token is over its request rate "
    "(EDGEPOS_RATE_LIMIT_PER_S); Retry-After says when to retry.",
    503: "Temporarily unavailable (e.g. the session store does not answer); retry.",
}


def errors(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for error statuses, all with the standard error body."""
    return {status: {"model": ErrorBody, "description": _DESCRIPTIONS[status]} for status in statuses}
