"""The one-write HTTP protocol (api/http_protocol.py) against uvicorn's own, over real sockets.

Two uvicorn servers in threads (uvloop, httptools) serve the same ASGI app, one with uvicorn's
``HttpToolsProtocol`` and one with ``OneWriteHttpToolsProtocol``; every connection's transport records
each ``write``. For every case (a whole body, 204, 304, HEAD, a stream, a body in parts, HTTP/1.0,
``Connection: close``, keep-alive, pipelining, 100-continue, the app's errors before and after the start,
uvicorn's length and type errors) the client receives the same bytes from both and the servers wrote
the same bytes in the same order; only the number of writes may differ, and it does where it should.
Then the service's own app behind the protocol: a batch answer in one write.
"""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from apihelp import ADMIN, batch_body, make_settings, rsu_payload
from edgepos.api.app import create_app
from edgepos.api.http_protocol import OneWriteHttpToolsProtocol
from edgepos.loadgen.localserver import free_port
from starlette.responses import JSONResponse, Response, StreamingResponse
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

pytestmark = pytest.mark.slow


class _Recorder:
    """A transport that records what is written through it and hands everything on."""

    def __init__(self, transport: asyncio.Transport, writes: list[bytes]) -> None:
        self._transport = transport
        self._writes = writes

    def write(self, data: bytes) -> None:
        self._writes.append(bytes(data))
        self._transport.write(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)


def _recording(base: type[HttpToolsProtocol], writes: list[bytes]) -> type[HttpToolsProtocol]:
    class Recording(base):  # type: ignore[valid-type,misc]
        def connection_made(self, transport: asyncio.Transport) -> None:
            super().connection_made(_Recorder(transport, writes))

    return Recording


async def _app(scope: dict[str, Any], receive: Any, send: Any) -> None:
    """The cases, by path."""
    if scope["type"] != "http":
        return
    path = scope["path"]
    if path == "/json":
        await JSONResponse({"fixes": [1.5, 2.5], "ok": True})(scope, receive, send)
    elif path == "/echo":  # reads the body (100-continue when asked)
        body = b""
        while True:
            message = await receive()
            body += message.get("body", b"")
            if not message.get("more_body", False):
                break
        await Response(body[::-1], media_type="application/octet-stream")(scope, receive, send)
    elif path == "/204":
        await Response(status_code=204)(scope, receive, send)
    elif path == "/304":
        await Response(status_code=304, headers={"etag": '"abc"'})(scope, receive, send)
    elif path == "/stream":

        async def chunks() -> Any:
            yield b"data: one\n\n"
            await asyncio.sleep(0.05)
            yield b"data: two\n\n"

        await StreamingResponse(chunks(), media_type="text/event-stream")(scope, receive, send)
    elif path == "/parts":
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"6")]})
        await send({"type": "http.response.body", "body": b"abc", "more_body": True})
        await send({"type": "http.response.body", "body": b"def"})
    elif path == "/connection-close":
        await Response(b"bye", headers={"connection": "close"})(scope, receive, send)
    elif path == "/fail-before":
        raise RuntimeError("before the start")
    elif path == "/fail-after":
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"4")]})
        raise RuntimeError("after the start")
    elif path == "/return-after-start":
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"4")]})
    elif path == "/too-long":
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"3")]})
        await send({"type": "http.response.body", "body": b"12345"})
    elif path == "/too-short":
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"9")]})
        await send({"type": "http.response.body", "body": b"12345"})
    elif path == "/wrong-type":
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"3")]})
        await send({"type": "http.response.start", "status": 200, "headers": []})
    else:
        await Response(b"not here", status_code=404)(scope, receive, send)


@contextlib.contextmanager
def _serving(app: Any, protocol: type[HttpToolsProtocol], **config: Any) -> Iterator[tuple[int, list[bytes]]]:
    """A uvicorn server with ``protocol`` in a thread; yields its port and the list of its writes."""
    writes: list[bytes] = []
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(
            app,
            host="127.0.0.1",
            port=port,
            loop="uvloop",
            http=_recording(protocol, writes),
            log_level="critical",
            access_log=False,
            date_header=False,
            server_header=False,
            **config,
        )
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30.0
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.01)
    try:
        yield port, writes
    finally:
        server.should_exit = True
        thread.join(timeout=30.0)


def _raw(port: int, request: bytes) -> bytes:
    """Send ``request`` on a new connection; everything received until the server closes it."""
    with socket.create_connection(("127.0.0.1", port), timeout=10.0) as sock:
        sock.sendall(request)
        received = b""
        while chunk := sock.recv(65536):
            received += chunk
        return received


def _get(path: str, method: str = "GET", extra: bytes = b"") -> bytes:
    return f"{method} {path} HTTP/1.1\r\nHost: t\r\n".encode() + extra + b"Connection: close\r\n\r\n"


RAW_CASES: dict[str, tuple[bytes, int, int]] = {
    # case: (request, writes by uvicorn's protocol, writes by the one-write protocol)
    "json": (_get("/json"), 2, 1),
    "head": (_get("/json", "HEAD"), 1, 1),
    "204": (_get("/204"), 2, 1),
    "304": (_get("/304"), 2, 1),
    "stream": (_get("/stream"), 4, 4),
    "parts": (_get("/parts"), 3, 2),
    "not found": (_get("/nowhere"), 2, 1),
    "connection close answer": (b"GET /connection-close HTTP/1.1\r\nHost: t\r\n\r\n", 2, 1),
    "http/1.0": (b"GET /json HTTP/1.0\r\nHost: t\r\n\r\n", 2, 1),
    "post": (
        b"POST /echo HTTP/1.1\r\nHost: t\r\nContent-Length: 5\r\nConnection: close\r\n\r\nhello",
        2,
        1,
    ),
    "fail before the start": (_get("/fail-before"), 2, 1),
    "fail after the start": (_get("/fail-after"), 1, 1),
    "return after the start": (_get("/return-after-start"), 1, 1),
    "too long": (_get("/too-long"), 1, 1),
    "too short": (_get("/too-short"), 2, 1),
    "wrong type": (_get("/wrong-type"), 1, 1),
    "pipelined": (
        b"GET /json HTTP/1.1\r\nHost: t\r\n\r\nHEAD /json HTTP/1.1\r\nHost: t\r\n\r\n" + _get("/204"),
        5,
        3,
    ),
}


@pytest.fixture(scope="module")
def servers() -> Iterator[dict[str, tuple[int, list[bytes]]]]:
    with (
        _serving(_app, HttpToolsProtocol, lifespan="off") as uvicorns,
        _serving(_app, OneWriteHttpToolsProtocol, lifespan="off") as ours,
    ):
        yield {"uvicorn": uvicorns, "one write": ours}


@pytest.mark.parametrize("case", sorted(RAW_CASES))
def test_the_same_bytes_in_fewer_writes(servers, case):
    request, uvicorn_writes, our_writes = RAW_CASES[case]
    received: dict[str, bytes] = {}
    written: dict[str, list[bytes]] = {}
    for name, (port, writes) in servers.items():
        writes.clear()
        received[name] = _raw(port, request)
        written[name] = list(writes)
    assert received["one write"] == received["uvicorn"]
    assert b"".join(written["one write"]) == b"".join(written["uvicorn"]) == received["uvicorn"]
    assert (len(written["uvicorn"]), len(written["one write"])) == (uvicorn_writes, our_writes)


def test_a_stream_head_goes_out_before_its_first_event(servers):
    port, writes = servers["one write"]
    writes.clear()
    _raw(port, _get("/stream"))
    assert writes[0].startswith(b"HTTP/1.1 200 OK\r\n") and writes[0].endswith(b"\r\n\r\n")
    assert b"transfer-encoding: chunked" in writes[0]


def test_keep_alive_and_expect_100_continue(servers):
    received: dict[str, list[tuple[int, list[tuple[str, str]], bytes]]] = {}
    written: dict[str, bytes] = {}
    for name, (port, writes) in servers.items():
        writes.clear()
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10.0)
        answers = []
        for method, path, body, headers in (
            ("GET", "/json", None, {}),
            ("POST", "/echo", b"abcdef", {"Expect": "100-continue"}),
            ("HEAD", "/json", None, {}),
            ("GET", "/204", None, {}),
            ("GET", "/json", None, {}),
        ):
            connection.request(method, path, body=body, headers=headers)
            response = connection.getresponse()
            answers.append((response.status, response.getheaders(), response.read()))
        connection.close()
        received[name] = answers
        written[name] = b"".join(writes)
    assert received["one write"] == received["uvicorn"]
    assert [status for status, _, _ in received["uvicorn"]] == [200, 200, 200, 204, 200]
    assert received["uvicorn"][1][2] == b"fedcba"
    assert b"HTTP/1.1 100 Continue\r\n\r\n" in written["uvicorn"]
    assert written["one write"] == written["uvicorn"]


def test_the_service_answers_a_batch_in_one_write(tmp_path: Path):
    app = create_app(make_settings(tmp_path))
    with (
        _serving(app, OneWriteHttpToolsProtocol) as (port, writes),
        httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as client,
    ):
        assert client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
        created = client.post("/v1/sessions", json={"vehicle_id": "one-write"}, headers=ADMIN)
        assert created.status_code == 201
        session = created.json()
        token = {"Authorization": f"Bearer {session['token']}"}
        writes.clear()
        answer = client.post(
            f"/v1/sessions/{session['session_id']}/batches",
            json=batch_body(1, 0, 20),
            headers={**token, "x-request-id": "one-write-batch"},
        )
    assert answer.status_code == 200, answer.text
    assert len(answer.json()["fixes"]) == 20
    assert answer.headers["x-request-id"] == "one-write-batch"
    assert len(writes) == 1 and writes[0].endswith(answer.content)
