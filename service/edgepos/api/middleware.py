"""ASGI middleware: request ids, access logs, metrics, the last-resort 500, admission control and
the body-size limit.

The size limit is enforced before any parsing: a Content-Length above the limit is refused at
once, and a body streamed without one is counted chunk by chunk and refused as soon as it passes
the limit. Both answer 413 with the standard error body.
"""

from __future__ import annotations

import asyncio
import logging
import math
import re
import time
import uuid
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from edgepos.api.errors import error_body
from edgepos.api.location import problems as location_problems
from edgepos.api.logs import request_id_var
from edgepos.api.metrics import Metrics

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

REQUEST_ID_HEADER = "x-request-id"
_REQUEST_ID_PATTERN = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")

access_logger = logging.getLogger("edgepos.access")
error_logger = logging.getLogger("edgepos.api")


def valid_request_id(value: str) -> bool:
    """True for an X-Request-ID the service keeps as the request's id (1-128 of ``A-Za-z0-9._:-``)."""
    return _REQUEST_ID_PATTERN.match(value) is not None


async def _send_error(
    send: Send,
    scope: Scope,
    status: int,
    code: str,
    message: str,
    extra_headers: tuple[tuple[bytes, bytes], ...] = (),
) -> None:
    """The error body of the service, or problem details on the location adapter's paths."""
    path = scope.get("path", "")
    if location_problems.is_location_path(path):
        body, media_type = (
            location_problems.problem_body(status, message, (), path),
            location_problems.MEDIA_TYPE,
        )
    else:
        body, media_type = error_body(code, message), "application/json"
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", media_type.encode()),
                (b"content-length", str(len(body)).encode()),
                *extra_headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class RequestContextMiddleware:
    """Outermost layer: request id (kept from X-Request-ID if well-formed), one JSON access-log
    line and metrics per request, and a generic 500 for any exception that escaped the routes."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = dict(scope.get("headers") or []).get(REQUEST_ID_HEADER.encode(), b"").decode("latin-1")
        request_id = incoming if valid_request_id(incoming) else uuid.uuid4().hex
        token = request_id_var.set(request_id)
        started = time.perf_counter()
        status = 500
        response_started = False

        async def send_with_id(message: Message) -> None:
            nonlocal status, response_started
            if message["type"] == "http.response.start":
                response_started = True
                status = int(message["status"])
                headers = list(message.get("headers") or [])
                headers.append((REQUEST_ID_HEADER.encode(), request_id.encode()))
                message["headers"] = headers
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        except Exception:
            error_logger.exception("unhandled error", extra={"event": "unhandled_error"})
            status = 500
            if not response_started:
                await _send_error(
                    send_with_id, scope, 500, "internal_error", "internal server error; the error was logged"
                )
        finally:
            elapsed = time.perf_counter() - started
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            self.metrics.observe_request(scope["method"], route, status, elapsed)
            access_logger.info(
                "request",
                extra={
                    "event": "request",
                    "method": scope["method"],
                    "route": route,
                    "path": scope["path"],
                    "status": status,
                    "duration_ms": round(elapsed * 1000.0, 3),
                },
            )
            request_id_var.reset(token)


class BodyLimitMiddleware:
    """Refuse request bodies above ``max_bytes`` with 413 before the app parses anything; the
    accepted body is buffered and handed on unchanged. ``path_limits`` gives some paths their own
    limit (path, or "/prefix/*" for every path under a prefix -> (bytes, name of the setting))."""

    def __init__(
        self, app: ASGIApp, max_bytes: int, path_limits: dict[str, tuple[int, str]] | None = None
    ) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.path_limits = dict(path_limits or {})

    def _limit(self, path: str) -> tuple[int, str]:
        """A path's own limit: an exact path, or a prefix given as ``"/prefix/*"``; else the default."""
        exact = self.path_limits.get(path)
        if exact is not None:
            return exact
        for pattern, limit in self.path_limits.items():
            if pattern.endswith("/*") and path.startswith(pattern[:-1]):
                return limit
        return self.max_bytes, "EDGEPOS_MAX_BODY_BYTES"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit, setting = self._limit(scope["path"])
        too_large = f"the request body exceeds {limit} bytes ({setting})"
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.strip().isdigit() and int(declared) > limit:
            await _send_error(send, scope, 413, "payload_too_large", too_large)
            return
        chunks: list[bytes] = []
        size = 0
        first: Message | None = None
        while True:
            message = await receive()
            if message["type"] != "http.request":
                first = message  # the client went away: let the app see it
                break
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > limit:
                await _send_error(send, scope, 413, "payload_too_large", too_large)
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        if first is None:
            first = {"type": "http.request", "body": b"".join(chunks), "more_body": False}
        await self.app(scope, replaying(first, receive), send)


def replaying(first: Message, receive: Receive) -> Receive:
    """``receive`` with ``first`` (already taken from it) handed out again first."""
    delivered = False

    async def replay() -> Message:
        nonlocal delivered
        if not delivered:
            delivered = True
            return first
        return await receive()

    return replay


class Admission:
    """At most ``max_inflight`` requests of this worker at work at once; the rest wait in line for up to
    ``queue_timeout_s``. Shared by :class:`AdmissionMiddleware` (each HTTP request) and the batch
    WebSocket (each frame), so that a batch takes the same place in line whichever way it came.

    Why: under overload an asyncio worker that starts every request at once interleaves them all,
    so each one's store round trip waits behind everyone else's CPU work and a healthy Redis looks
    like a timeout. Bounding the work in progress keeps each request short; the waiting costs
    nothing but latency, which the metrics show."""

    def __init__(self, max_inflight: int, queue_timeout_s: float, metrics: Metrics) -> None:
        self.slots = asyncio.Semaphore(max_inflight)
        self.queue_timeout_s = queue_timeout_s
        self.metrics = metrics

    @property
    def retry_after_s(self) -> int:
        """The Retry-After of a request that found no slot."""
        return max(1, math.ceil(self.queue_timeout_s / 10))

    @property
    def busy_message(self) -> str:
        return (
            f"this worker is busy: the request waited {self.queue_timeout_s:g} s "
            "(EDGEPOS_QUEUE_TIMEOUT_S) without a free slot; retry after the Retry-After seconds"
        )

    async def acquire(self) -> bool:
        """Wait for a slot: True once holding one (give it back with :meth:`release`), False when the
        wait timed out."""
        if not self.slots.locked():  # a slot free and nobody in line: taken now, no timed wait (a task)
            return await self.slots.acquire()
        self.metrics.waiting.inc()
        try:
            await asyncio.wait_for(self.slots.acquire(), self.queue_timeout_s)
        except TimeoutError:
            return False
        finally:
            self.metrics.waiting.dec()
        return True

    def release(self) -> None:
        self.slots.release()


class AdmissionMiddleware:
    """Each HTTP request waits for a slot of :class:`Admission` before its body is read, and is answered
    503 with Retry-After if none frees up in time. Probes and metrics bypass the line so that an
    orchestrator does not restart a busy worker.
    """

    BYPASS = frozenset({"/healthz", "/readyz", "/metrics", "/v1/stream/fixes"})
    """Probes, metrics and the fix stream, whose responses last as long as the consumer stays (a stream
    would hold a slot for hours; EDGEPOS_STREAM_MAX_CONSUMERS bounds the streams instead)."""

    def __init__(self, app: ASGIApp, admission: Admission) -> None:
        self.app = app
        self.admission = admission

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in self.BYPASS:
            await self.app(scope, receive, send)
            return
        admission = self.admission
        if not await admission.acquire():
            retry_after = str(admission.retry_after_s).encode()
            await _send_error(
                send, scope, 503, "unavailable", admission.busy_message, ((b"retry-after", retry_after),)
            )
            return
        try:
            await self.app(scope, receive, send)
        finally:
            admission.release()
