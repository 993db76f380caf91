"""A real server with a fix stream open stops on SIGTERM: the stream never ends by itself, so the worker
bounds its graceful shutdown (uvicorn would otherwise wait for every consumer to leave)."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import time
from pathlib import Path

import httpx
import pytest
from apihelp import ADMIN, ADMIN_KEY
from edgepos.loadgen.localserver import PORT_PLACEHOLDER, clean_environment, free_port, serve_command

pytestmark = pytest.mark.slow


def test_sigterm_with_a_stream_open_stops_the_server(tmp_path: Path):
    port = free_port()
    command = [part.replace(PORT_PLACEHOLDER, str(port)) for part in serve_command(1)]
    environment = clean_environment(EDGEPOS_ADMIN_KEY=ADMIN_KEY, EDGEPOS_LOG_LEVEL="warning")
    with open(tmp_path / "server.log", "wb") as log:
        process = subprocess.Popen(
            command, env=environment, stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path
        )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 300.0
        while True:
            assert process.poll() is None, (tmp_path / "server.log").read_text()
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{base}/readyz", timeout=1.0).status_code == 200:
                    break
            assert time.monotonic() < deadline, "the server did not become ready"
            time.sleep(0.1)
        with httpx.stream(
            "GET", f"{base}/v1/stream/fixes", headers=ADMIN, timeout=httpx.Timeout(60.0)
        ) as stream:
            assert stream.status_code == 200
            lines = stream.iter_lines()
            next(lines)  # connected: the stream's preamble
            process.send_signal(signal.SIGTERM)
            # the server ends the stream (cancelled after its graceful-shutdown bound) and exits
            with contextlib.suppress(httpx.HTTPError):
                for _ in lines:
                    pass
        assert process.wait(timeout=60.0) in (0, -signal.SIGTERM)  # uvicorn re-raises the signal once stopped
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
