"""uvicorn's httptools protocol, writing a complete response in one socket write.

uvicorn writes a response's status line and headers when the app sends ``http.response.start`` and its
body when the app sends ``http.response.body``: two ``transport.write`` calls, two ``send`` system calls
(and, with TCP_NODELAY, two segments) per answer. Under load that was 11-13 % of a worker's samples
(``bench/profile_service.py --gil``), for a batch answer sent whole in one body message.

Here, when the start message declares a Content-Length (or neither framing header, as uvicorn allows
for 204 and 304), the head is held back and written with the next message's first write: a batch answer,
sent whole in one body message, then leaves in one write. All the rest is uvicorn's code: it builds the
head, checks the body against the length, closes, keeps the connection alive. A chunked (streamed)
response's head goes out at once, as before, so a stream's client sees it before the first event; a held
head goes out alone when the next message writes nothing (HEAD, uvicorn refusing the message, the app
ending or failing before the body), before uvicorn closes the connection. The bytes on the wire are
uvicorn's, in order, in fewer writes (tests/api/test_api_http_protocol.py compares them over a real
socket). WebSocket upgrades go to uvicorn's WebSocket protocol as before.
"""

from __future__ import annotations

import asyncio
from typing import Any

from uvicorn._types import ASGISendEvent
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol, RequestResponseCycle


class _HeadCatcher:
    """Stands in for the transport while uvicorn's cycle handles a start message: keeps the head it writes."""

    __slots__ = ("head",)

    def __init__(self) -> None:
        self.head: bytes | None = None

    def write(self, data: bytes) -> None:
        self.head = data


class _HeldHead:
    """Stands in for the transport between a response's start and its next message: the head goes out
    with the first write, or alone before the transport closes, or when that message wrote nothing."""

    __slots__ = ("head", "transport")

    def __init__(self, transport: asyncio.Transport, head: bytes) -> None:
        self.transport = transport
        self.head = head

    def write(self, data: bytes) -> None:
        head, self.head = self.head, b""
        self.transport.write(head + data)

    def flush(self) -> None:
        if self.head and not self.transport.is_closing():
            self.transport.write(self.head)
        self.head = b""

    def close(self) -> None:
        self.flush()
        self.transport.close()

    def is_closing(self) -> bool:
        return self.transport.is_closing()


class OneWriteCycle(RequestResponseCycle):
    """A request/response cycle whose non-chunked response head goes out with the body's first write."""

    async def send(self, message: ASGISendEvent) -> None:
        """uvicorn's ``send``, with the head of a non-chunked response held until the next message."""
        held = self.transport
        if isinstance(held, _HeldHead):
            try:
                await super().send(message)
            finally:
                self.transport = held.transport
                held.flush()  # HEAD, a refused message, a disconnect: nothing was written
            return
        if self.response_started:
            await super().send(message)
            return
        if self.flow.write_paused and not self.disconnected:
            await self.flow.drain()  # as uvicorn does first: then nothing below awaits
        transport = held
        catcher = _HeadCatcher()
        self.transport = catcher  # type: ignore[assignment]  # a start message only writes
        try:
            await super().send(message)
        finally:
            self.transport = transport
        if catcher.head is None:  # disconnected: nothing written
            return
        if self.chunked_encoding:  # a stream: its head at once, as uvicorn writes it
            transport.write(catcher.head)
        else:
            self.transport = _HeldHead(transport, catcher.head)  # type: ignore[assignment]


class OneWriteHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol whose cycles are :class:`OneWriteCycle` (``uvicorn.run(http=...)``)."""

    def on_headers_complete(self) -> None:
        """uvicorn's, then the new cycle made a :class:`OneWriteCycle` before its task first runs (the
        task looks ``send`` up when it starts, after this callback returns)."""
        super().on_headers_complete()
        cycle: Any = self.cycle
        if type(cycle) is RequestResponseCycle:
            cycle.__class__ = OneWriteCycle
