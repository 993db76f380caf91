"""Batches over one WebSocket: ``/v1/sessions/{session_id}/ws`` (the protocol is in docs/service.md).

For vehicles that keep a link open: each text frame is one batch, exactly the body of
``POST /v1/sessions/{id}/batches``, and each answer one text frame
``{"status", "seq", "frame", "request_id", "retry_after", "body"}`` whose ``status`` and ``body`` are what
the POST would have answered. Each frame goes down the POST route's own path (the worker's admission
line, the session check of ``auth.authenticate_session`` with the token's request budget, the body's
validation, ``session_service.apply_batch`` with its scheduler turn, compare-and-set and replay), so seq
rules, idempotency and errors are the same by construction; the handshake is checked the same way.
Frames are read one at a time: one batch of the connection is in flight, as over HTTP with one
connection. A worker holds at most EDGEPOS_WS_MAX_CONNECTIONS links (503 at the handshake beyond).

Close codes: 1000 after EDGEPOS_WS_IDLE_TIMEOUT_S without a frame, 1008 after a frame answered that
the session has ended or been superseded, 1009 for a frame over EDGEPOS_MAX_BODY_BYTES; the reason is a
short JSON object ``{"status", "code"}`` (a close reason holds at most 123 bytes). A refused handshake
gets the HTTP error response the POST route would give (status, headers and error body) where the
server supports WebSocket denial responses (uvicorn does), else a close with 1008 before accepting.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
import uuid
from typing import Any

from fastapi import WebSocket
from pydantic import ValidationError
from starlette.websockets import WebSocketDisconnect

from edgepos.api import session_service
from edgepos.api.auth import authenticate_session, bearer_secret
from edgepos.api.context import AppContext
from edgepos.api.errors import (
    ApiError,
    error_body,
    error_response,
    invalid_request_error,
    store_unavailable_error,
)
from edgepos.api.logs import request_id_var
from edgepos.api.measurement_schemas import BatchIn
from edgepos.api.middleware import REQUEST_ID_HEADER, valid_request_id
from edgepos.api.schemas import ProblemModel
from edgepos.store.base import StoreUnavailable

logger = logging.getLogger("edgepos.api")
access_logger = logging.getLogger("edgepos.access")

ROUTE = "/v1/sessions/{session_id}/ws"
CLOSE_NORMAL = 1000
CLOSE_POLICY_VIOLATION = 1008
CLOSE_TOO_BIG = 1009
FULL_RETRY_AFTER_S = 5
"""Retry-After of a handshake refused because the worker holds its maximum of links."""
ENDING_CODES = frozenset({"superseded", "not_found", "unauthorized"})
"""Answers after which the credential opens nothing more (the session was superseded, or deleted, revoked or
expired: 409 superseded, else as over HTTP 401 for its token and 404 for the admin key): the frame is sent,
then the link closes."""


def close_reason(status: int, code: str) -> str:
    """The close frame's reason: ``{"status", "code"}`` (a reason holds at most 123 bytes of UTF-8)."""
    return json.dumps({"status": status, "code": code}, separators=(",", ":"))


def answer_frame(
    status: int, seq: int | None, frame: int, request_id: str, retry_after: int | None, body: bytes
) -> str:
    """One answer frame. ``body`` is the POST route's JSON body, spliced in as it is (not parsed again)."""
    head = json.dumps(
        {"status": status, "seq": seq, "frame": frame, "request_id": request_id, "retry_after": retry_after},
        separators=(",", ":"),
    )
    return f'{head[:-1]},"body":{body.decode()}}}'


def _seq_of(document: Any) -> int | None:
    """The frame's seq when it has a well-formed one, echoed even when the batch is refused."""
    seq = document.get("seq") if isinstance(document, dict) else None
    return seq if isinstance(seq, int) and not isinstance(seq, bool) else None


def decode_frame(text: str) -> tuple[Any, ApiError | None]:
    """The frame's JSON document, or the 422 the POST route gives a body that is not JSON (naming the line
    and column of the syntax error)."""
    try:
        return json.loads(text), None
    except json.JSONDecodeError as error:  # the error FastAPI raises for a POST body that is not JSON
        problem = {
            "type": "json_invalid",
            "loc": ("body", error.pos),
            "msg": "JSON decode error",
            "ctx": {"error": error.msg},
        }
        return None, invalid_request_error([problem], error.doc)


def one_pass_batch(text: str) -> BatchIn | None:
    """The frame's batch validated straight from its text, or None: then the document is decoded and
    validated as the POST route does, which words every refusal."""
    try:
        return BatchIn.model_validate_json(text)
    except ValidationError:
        return None


def validate_batch(document: Any) -> BatchIn:
    """The document as a batch, or the POST route's 422 naming every field that does not fit the schema."""
    try:
        return BatchIn.model_validate(document, from_attributes=True)  # as FastAPI validates a body
    except ValidationError as error:
        raise invalid_request_error(error.errors(), document) from None


def _retry_after(error: ApiError) -> int | None:
    value = error.headers.get("Retry-After")
    return int(value) if value is not None and value.isdigit() else None


class BatchSocket:
    """One vehicle's batch connection: reads a frame, answers it, reads the next."""

    def __init__(self, websocket: WebSocket, context: AppContext, session_id: str) -> None:
        self.websocket = websocket
        self.context = context
        self.session_id = session_id
        self.secret = bearer_secret(websocket)
        incoming = websocket.headers.get(REQUEST_ID_HEADER, "")
        self.connection_id = incoming if valid_request_id(incoming) else uuid.uuid4().hex
        self.frames = 0

    async def serve(self) -> None:
        """Check the credential at the handshake, then answer frames until the vehicle leaves, the link
        idles out, a frame is too large, or the session ends."""
        token = request_id_var.set(self.connection_id)
        started = time.perf_counter()
        close = "client"
        try:
            try:
                await authenticate_session(self.context, self.websocket, self.session_id, self.secret)
                self._check_room()
            except (ApiError, StoreUnavailable) as refusal:
                error = refusal if isinstance(refusal, ApiError) else store_unavailable_error(refusal)
                await self._deny(error)
                close = f"refused:{error.code}"
                return
            self.context.batch_sockets += 1
            try:
                await self.websocket.accept()
                close = await self._answer_frames()
            finally:
                self.context.batch_sockets -= 1
        except WebSocketDisconnect:
            close = "client"
        finally:
            access_logger.info(
                "websocket",
                extra={
                    "event": "websocket",
                    "route": ROUTE,
                    "frames": self.frames,
                    "close": close,
                    "duration_ms": round((time.perf_counter() - started) * 1000.0, 3),
                },
            )
            request_id_var.reset(token)

    def _check_room(self) -> None:
        """503 with Retry-After when this worker already holds EDGEPOS_WS_MAX_CONNECTIONS links."""
        most = self.context.settings.ws_max_connections
        if self.context.batch_sockets >= most:
            raise ApiError(
                "unavailable",
                f"this worker holds its maximum of {most} batch WebSockets (EDGEPOS_WS_MAX_CONNECTIONS); "
                "retry after the Retry-After seconds, or send the batch with POST",
                headers={"Retry-After": str(FULL_RETRY_AFTER_S)},
            )

    async def _deny(self, error: ApiError) -> None:
        """Refuse the handshake: the POST route's HTTP error response, or a policy-violation close."""
        self.context.metrics.observe_request("WS", ROUTE, error.status, 0.0)
        if "websocket.http.response" in self.websocket.scope.get("extensions", {}):
            await self.websocket.send_denial_response(error_response(error))
        else:
            await self.websocket.close(CLOSE_POLICY_VIOLATION, close_reason(error.status, error.code))

    async def _answer_frames(self) -> str:
        settings = self.context.settings
        limit = settings.max_body_bytes
        while True:
            try:
                message = await asyncio.wait_for(self.websocket.receive(), settings.ws_idle_timeout_s)
            except TimeoutError:
                await self.websocket.close(CLOSE_NORMAL, close_reason(408, "idle_timeout"))
                return "idle"
            if message["type"] == "websocket.disconnect":
                return "client"
            self.frames += 1
            text = message.get("text")
            if text is not None and len(text) > limit // 4 and len(text.encode()) > limit:
                await self.websocket.close(CLOSE_TOO_BIG, close_reason(413, "payload_too_large"))
                return "too_big"
            started = time.perf_counter()
            request_id = f"{self.connection_id}.{self.frames}"
            token = request_id_var.set(request_id)  # the frame's log lines carry its own request id
            try:
                status, seq, body, error = await self._answer(text)
                retry_after = None if error is None else _retry_after(error)
                await self.websocket.send_text(
                    answer_frame(status, seq, self.frames, request_id, retry_after, body)
                )
                elapsed = time.perf_counter() - started
                self.context.metrics.observe_request("WS", ROUTE, status, elapsed)
                access_logger.info(  # one line per batch, as a POST gets
                    "request",
                    extra={
                        "event": "request",
                        "method": "WS",
                        "route": ROUTE,
                        "path": self.websocket.url.path,
                        "status": status,
                        "duration_ms": round(elapsed * 1000.0, 3),
                    },
                )
            finally:
                request_id_var.reset(token)
            if error is not None and error.code in ENDING_CODES:
                await self.websocket.close(CLOSE_POLICY_VIOLATION, close_reason(error.status, error.code))
                return f"ended:{error.code}"

    async def _answer(self, text: str | None) -> tuple[int, int | None, bytes, ApiError | None]:
        """Status, echoed seq, body and the refusal (None on success) of one frame, in the POST route's
        order: a place in the worker's line; the credential checked against the session as it is now,
        which charges the token's request budget (as every POST is checked: a session deleted, revoked,
        expired or superseded meanwhile is refused alike); the body; the batch, applied on the record
        that check read, as the POST route does."""
        # a frame that validates in one pass from its text skips the document (api/one_pass_body.py)
        ready = None if text is None else one_pass_batch(text)
        document, syntax_error = (None, None) if text is None or ready is not None else decode_frame(text)
        seq = ready.seq if ready is not None else _seq_of(document)
        admission = self.context.admission
        if admission is not None and not await admission.acquire():
            retry_after = {"Retry-After": str(admission.retry_after_s)}
            error = ApiError("unavailable", admission.busy_message, headers=retry_after)
            return error.status, seq, error_body(error.code, error.message), error
        try:
            _principal, record = await authenticate_session(
                self.context, self.websocket, self.session_id, self.secret, for_batch=True
            )
            if text is None:
                raise ApiError(
                    "unsupported_media_type",
                    "send each batch as a text frame of JSON (UTF-8); this frame was binary",
                    [ProblemModel(index=None, field="frame", reason="must be a text frame")],
                )
            if syntax_error is not None:
                raise syntax_error
            batch = ready if ready is not None else validate_batch(document)
            body = await session_service.apply_batch(self.context, self.session_id, batch, record)
            return 200, seq, body, None
        except ApiError as refusal:
            error = refusal
        except StoreUnavailable as unavailable:
            error = store_unavailable_error(unavailable)
        except Exception:  # a bug: logged with its traceback and answered as the HTTP routes' generic 500
            logger.exception("unhandled error", extra={"event": "unhandled_error"})
            error = ApiError("internal_error", "internal server error; the error was logged")
        finally:
            if admission is not None:
                admission.release()
        return error.status, seq, error_body(error.code, error.message, error.problems), error
