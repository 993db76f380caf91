"""Exceptions raised by the client: one class per server error code, all under :class:`EdgeposError`.

Each carries the server's machine ``code``, its human ``message``, the ``problems`` it listed
(measurement index, field, reason), the HTTP ``status`` and the ``request_id`` the server gave
the request (quote it when asking the operator about a failure).
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import httpx
from pydantic import ValidationError

from edgepos_client.models import ErrorBody, Problem


class EdgeposError(Exception):
    """A request the server refused (or could not answer); ``status`` is None if nothing came back."""

    def __init__(
        self,
        code: str,
        message: str,
        *,
        status: int | None = None,
        problems: list[Problem] | None = None,
        request_id: str | None = None,
    ) -> None:
        self.code = code
        self.message = message
        self.status = status
        self.problems = list(problems or [])
        self.request_id = request_id
        super().__init__(self._describe())

    def _describe(self) -> str:
        head = (
            f"{self.status} {self.code}: {self.message}"
            if self.status is not None
            else f"{self.code}: {self.message}"
        )
        details = "; ".join(
            f"{problem.field}{'' if problem.index is None else f' (#{problem.index})'}: {problem.reason}"
            for problem in self.problems
        )
        return f"{head} [{details}]" if details else head


class InvalidRequest(EdgeposError):
    """422 invalid_request: the body or a parameter was refused; ``problems`` lists each reason."""


class EstimationFailed(EdgeposError):
    """422 estimation_failed: the filter could not process the batch; the session is unchanged."""


class Unauthorized(EdgeposError):
    """401: missing or invalid bearer credential (unknown, revoked or rotated key, expired token)."""


class Forbidden(EdgeposError):
    """403: the credential is valid but does not open this resource."""


class NotFound(EdgeposError):
    """404: no such RSU, session (perhaps expired) or route."""


class MethodNotAllowed(EdgeposError):
    """405: the route does not accept this method."""


class Conflict(EdgeposError):
    """409: the batch's seq does not follow the session's last applied seq (or reuses it with a new body),
    or the vehicle is already registered."""


class Superseded(Conflict):
    """409 superseded: the vehicle opened a newer session, its only live one now; this session's token
    opens nothing any more (the message names the newer session)."""


class PayloadTooLarge(EdgeposError):
    """413: the request body exceeds the server's limit."""


class RateLimited(EdgeposError):
    """429: slow down (too many requests, failed authentications or sessions opened); ``retry_after`` is
    the server's Retry-After in seconds when it sent one."""

    def __init__(
        self,
        code: str,
        message: str,
        *,
        retry_after: float | None = None,
        status: int | None = None,
        problems: list[Problem] | None = None,
        request_id: str | None = None,
    ) -> None:
        self.retry_after = retry_after
        super().__init__(code, message, status=status, problems=problems, request_id=request_id)


class TooManySessions(RateLimited):
    """429 too_many_sessions: the server holds its maximum number of sessions."""


class Unavailable(EdgeposError):
    """503: temporarily unavailable; the same request may be retried."""


class ServerError(EdgeposError):
    """500 or another unexpected status: a server fault."""


class TransportError(EdgeposError):
    """No answer: connection refused or broken, or a timeout, after every allowed attempt."""


ERROR_CLASSES: Mapping[str, type[EdgeposError]] = {
    "invalid_request": InvalidRequest,
    "estimation_failed": EstimationFailed,
    "unauthorized": Unauthorized,
    "forbidden": Forbidden,
    "not_found": NotFound,
    "method_not_allowed": MethodNotAllowed,
    "conflict": Conflict,
    "superseded": Superseded,
    "payload_too_large": PayloadTooLarge,
    "too_many_sessions": TooManySessions,
    "rate_limited": RateLimited,
    "unavailable": Unavailable,
    "internal_error": ServerError,
}

_CODE_OF_STATUS: Mapping[int, str] = {
    400: "invalid_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    409: "conflict",
    413: "payload_too_large",
    422: "invalid_request",
    429: "rate_limited",
    503: "unavailable",
}


def _retry_after(value: str | float | None) -> float | None:
    if value is None:
        return None
    try:
        seconds = float(value)
    except ValueError:
        return None  # an HTTP date: too rare from this server to be worth parsing
    return seconds if seconds >= 0 else None


def error_from_response(response: httpx.Response) -> EdgeposError:
    """The exception for a non-2xx answer, from the standard error body when there is one."""
    return error_from_answer(
        response.status_code,
        response.content,
        retry_after=response.headers.get("retry-after"),
        request_id=response.headers.get("x-request-id"),
        reason_phrase=response.reason_phrase,
    )


def error_from_answer(
    status: int,
    content: bytes,
    *,
    retry_after: str | float | None = None,
    request_id: str | None = None,
    reason_phrase: str = "",
) -> EdgeposError:
    """The exception for a refusal with this status and body: an HTTP answer, a refused WebSocket handshake,
    or an error frame of the batch WebSocket (which carries the same status and body)."""
    try:
        detail = ErrorBody.model_validate_json(content).error
        code, message, problems = detail.code, detail.message, detail.problems
    except (ValidationError, json.JSONDecodeError, UnicodeDecodeError):
        code = _CODE_OF_STATUS.get(status, "internal_error" if status >= 500 else "invalid_request")
        text = content.decode("utf-8", "replace").strip()
        message = text[:500] if text else f"HTTP {status} {reason_phrase}".rstrip()
        problems = []
    cls = ERROR_CLASSES.get(code)
    if cls is None:  # a code this client does not know yet: fall back on the status
        cls = ERROR_CLASSES.get(
            _CODE_OF_STATUS.get(status, ""), ServerError if status >= 500 else EdgeposError
        )
    if issubclass(cls, RateLimited):
        return cls(
            code,
            message,
            status=status,
            problems=problems,
            request_id=request_id,
            retry_after=_retry_after(retry_after),
        )
    return cls(code, message, status=status, problems=problems, request_id=request_id)
