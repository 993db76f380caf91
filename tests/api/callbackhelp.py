"""A real HTTP receiver on 127.0.0.1 for notification tests: records every POSTed JSON body and answers
with the status the test sets."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any


class Receiver:
    def __init__(self) -> None:
        self.bodies: list[dict[str, Any]] = []
        self.times: list[float] = []
        self.answered: list[int] = []  # the status each body was answered with
        self.status = 204
        self.url = ""
        self._lock = threading.Lock()

    def record(self, body: dict[str, Any]) -> int:
        with self._lock:
            self.bodies.append(body)
            self.times.append(time.monotonic())
            self.answered.append(self.status)
            return self.status

    def received(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self.bodies)

    def answered_with(self, status: int) -> list[dict[str, Any]]:
        """The bodies this receiver answered with ``status``, in the order they came."""
        with self._lock:
            return [body for body, answer in zip(self.bodies, self.answered, strict=True) if answer == status]

    def wait_for(
        self, check: Callable[[list[dict[str, Any]]], bool], timeout_s: float = 20.0
    ) -> list[dict[str, Any]]:
        """The bodies once ``check`` holds for them; fails the test after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            bodies = self.received()
            if check(bodies):
                return bodies
            time.sleep(0.02)
        raise AssertionError(f"not received in {timeout_s} s; got {self.received()}")


@contextmanager
def receiver() -> Iterator[Receiver]:
    """A receiver listening on 127.0.0.1 (a free port) at ``receiver.url``."""
    state = Receiver()

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            length = int(self.headers.get("Content-Length", "0"))
            status = state.record(json.loads(self.rfile.read(length)))
            self.send_response(status)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, format: str, *args: Any) -> None:
            return

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    state.url = f"http://127.0.0.1:{server.server_address[1]}/notify"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield state
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
