"""A session's batches over one WebSocket (``/v1/sessions/{id}/ws``): :class:`BatchSocket` (blocking) and
:class:`AsyncBatchSocket`, from ``client.websocket(session)``.

Each batch is the bytes the HTTP method would POST, sent as one text frame; the server answers each
with one frame carrying the HTTP status and body the POST would have got, so :meth:`send_batch` returns
the same fixes and raises the same :class:`EdgeposError` subclasses as ``client.send_batch``. One batch
is in flight at a time. A link that breaks (or idles out) is opened again and the same bytes are sent
with the same seq, which the server answers once; a 503 answer is retried likewise, both within the
client's retry policy.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Self

import httpx

try:
    import websockets  # noqa: F401  (an optional dependency: named in the error below when missing)
except ImportError as missing:
    raise ImportError(
        "the batch WebSocket needs the websockets package: pip install 'edgepos-client[websocket]'"
    ) from missing
from websockets.asyncio.client import ClientConnection as AsyncConnection
from websockets.asyncio.client import connect as async_connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus
from websockets.protocol import State
from websockets.sync.client import ClientConnection, connect

from edgepos_client import _protocol as protocol
from edgepos_client._protocol import Call, Calls, MeasurementLike, RetryPolicy, Session
from edgepos_client.errors import EdgeposError, PayloadTooLarge, TransportError, error_from_answer
from edgepos_client.models import BatchResult, Fix

MAX_ANSWER_BYTES = 64 * 1024 * 1024
"""Largest answer frame accepted (a batch of many epochs with include_state can be a few MB)."""

CLOSE_TIMEOUT_S = 2.0
"""How long closing waits for the server's close frame."""

_CLOSE_REFUSALS = frozenset({1008, 1009})
"""Close codes that refuse (the session ended, a frame too large): raised, not retried."""


@dataclass(frozen=True)
class SocketTarget:
    """Where and how a batch socket connects: the ``ws(s)://`` URL, the bearer, the retry policy, the
    per-attempt timeout (s) and whether frames are compressed (permessage-deflate)."""

    url: str
    call: Call
    policy: RetryPolicy
    timeout: float
    compression: bool

    @classmethod
    def of(
        cls,
        base_url: httpx.URL,
        calls: Calls,
        session: Session | str,
        policy: RetryPolicy,
        timeout: float,
        compression: bool,
    ) -> SocketTarget:
        call = calls.batch_socket(session)
        scheme = {"http": "ws", "https": "wss"}.get(base_url.scheme)
        if scheme is None:
            raise ValueError(
                f"the client's base URL must be http or https for a WebSocket, not {base_url.scheme!r}"
            )
        url = base_url.copy_with(scheme=scheme, raw_path=base_url.raw_path.rstrip(b"/") + call.path.encode())
        return cls(str(url), call, policy, timeout, compression)

    def options(self) -> dict[str, Any]:
        """The keyword arguments of websockets' ``connect`` (sync and asyncio alike)."""
        headers = {} if not self.call.credential else {"Authorization": f"Bearer {self.call.credential}"}
        return {
            "additional_headers": headers,
            "open_timeout": self.timeout,
            "close_timeout": CLOSE_TIMEOUT_S,
            "max_size": MAX_ANSWER_BYTES,
            "compression": "deflate" if self.compression else None,
        }


def _retry(target: SocketTarget, error: EdgeposError, attempt: int) -> bool:
    return target.policy.may_retry_status(target.call, error.status or 0, attempt)


def settle(
    target: SocketTarget, session: Session | str, seq: int, frame: str | bytes, attempt: int
) -> list[Fix] | None:
    """The fixes of an answer frame; None when it is a 503 to send again; else its error is raised."""
    answer = json.loads(frame)
    status, body = int(answer["status"]), answer["body"]
    if status == 200:
        return protocol.result_fixes(session, seq, BatchResult.model_validate(body))
    error = error_from_answer(
        status,
        json.dumps(body).encode(),
        retry_after=answer.get("retry_after"),
        request_id=answer.get("request_id"),
    )
    if _retry(target, error, attempt):
        return None
    raise error


def failure(target: SocketTarget, error: Exception, attempt: int) -> EdgeposError | None:
    """What a failed attempt means: None to open the link again and resend, else the error to raise."""
    if isinstance(error, InvalidStatus):  # the handshake refused with the HTTP error the POST route gives
        response = error.response
        refusal = error_from_answer(
            response.status_code,
            bytes(response.body or b""),
            retry_after=response.headers.get("retry-after"),
            request_id=response.headers.get("x-request-id"),
            reason_phrase=response.reason_phrase,
        )
        return None if _retry(target, refusal, attempt) else refusal
    if isinstance(error, ConnectionClosed) and error.rcvd is not None and error.rcvd.code in _CLOSE_REFUSALS:
        return _closed_refusal(error.rcvd.code, error.rcvd.reason)
    if attempt < target.policy.retries:
        return None
    kind = "timeout" if isinstance(error, TimeoutError) else "connection_error"
    return TransportError(
        kind,
        f"the batch WebSocket {target.call.path} got no answer after {attempt + 1} attempt(s): "
        f"{type(error).__name__}: {error}",
    )


def _closed_refusal(code: int, reason: str) -> EdgeposError:
    """The error named by a refusing close frame's JSON reason ``{"status", "code"}``."""
    try:
        named = json.loads(reason)
        status, error_code = int(named["status"]), str(named["code"])
    except (ValueError, KeyError, TypeError):
        status, error_code = (413, "payload_too_large") if code == 1009 else (409, "conflict")
    message = f"the server closed the batch WebSocket ({code}): {error_code}"
    if code == 1009:
        return PayloadTooLarge(
            "payload_too_large", message + " (the frame exceeds the server's body limit)", status=413
        )
    return error_from_answer(
        status, json.dumps({"error": {"code": error_code, "message": message, "problems": []}}).encode()
    )


_FAILURES = (InvalidHandshake, ConnectionClosed, OSError, TimeoutError)
"""What an attempt may fail with (InvalidStatus, a refused handshake, is an InvalidHandshake)."""


class BatchSocket:
    """A session's batch WebSocket (blocking): :meth:`send_batch` as ``EdgeposClient.send_batch``. Use as a
    context manager, or call :meth:`close`. The link opens with the first batch."""

    def __init__(self, target: SocketTarget, session: Session | str, calls: Calls) -> None:
        self._target = target
        self._session = session
        self._calls = calls
        self._link: ClientConnection | None = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.close()

    def send_batch(
        self, measurements: Sequence[MeasurementLike], seq: int | None = None, *, include_state: bool = False
    ) -> list[Fix]:
        """Send one batch and return one fix per epoch, in time order (``seq`` defaults to the handle's
        last seq + 1)."""
        number = protocol.next_seq(self._session, seq)
        frame = self._calls.batch(self._session, measurements, number, include_state).body or b""
        text = frame.decode()
        attempt = 0
        while True:
            try:
                if self._link is not None and self._link.protocol.state is not State.OPEN:
                    self.close()  # closed meanwhile (the server's idle timeout): a new link, not a retry
                if self._link is None:
                    # entered as a context (closed by close()): websockets 17 warns on a bare connect()
                    self._link = connect(self._target.url, **self._target.options()).__enter__()
                self._link.send(text)
                fixes = settle(
                    self._target, self._session, number, self._link.recv(self._target.timeout), attempt
                )
                if fixes is not None:
                    return fixes
            except _FAILURES as error:
                self.close()  # whatever the link still holds would answer the wrong frame
                refusal = failure(self._target, error, attempt)
                if refusal is not None:
                    raise refusal from error
            time.sleep(self._target.policy.delay(attempt))
            attempt += 1


class AsyncBatchSocket:
    """A session's batch WebSocket (asyncio): :meth:`send_batch` as ``AsyncEdgeposClient.send_batch``. Use
    as an async context manager, or await :meth:`close`. The link opens with the first batch."""

    def __init__(self, target: SocketTarget, session: Session | str, calls: Calls) -> None:
        self._target = target
        self._session = session
        self._calls = calls
        self._link: AsyncConnection | None = None

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    async def close(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            await link.close()

    async def send_batch(
        self, measurements: Sequence[MeasurementLike], seq: int | None = None, *, include_state: bool = False
    ) -> list[Fix]:
        """Send one batch and return one fix per epoch, in time order (``seq`` defaults to the handle's
        last seq + 1)."""
        number = protocol.next_seq(self._session, seq)
        frame = self._calls.batch(self._session, measurements, number, include_state).body or b""
        text = frame.decode()
        attempt = 0
        while True:
            try:
                if self._link is not None and self._link.protocol.state is not State.OPEN:
                    await (
                        self.close()
                    )  # closed meanwhile (the server's idle timeout): a new link, not a retry
                if self._link is None:
                    self._link = await async_connect(self._target.url, **self._target.options())
                await self._link.send(text)
                answer = await asyncio.wait_for(self._link.recv(), self._target.timeout)
                fixes = settle(self._target, self._session, number, answer, attempt)
                if fixes is not None:
                    return fixes
            except _FAILURES as error:
                await self.close()
                refusal = failure(self._target, error, attempt)
                if refusal is not None:
                    raise refusal from error
            await asyncio.sleep(self._target.policy.delay(attempt))
            attempt += 1
