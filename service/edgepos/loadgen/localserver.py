"""Run a server process on a free loopback port for the length of a ``with`` block.

Used by the service benchmark and the tests that drive a real server over a real socket. The
child gets a clean ``EDGEPOS_*`` environment (only what the caller passes), writes its output to
a log file, and is terminated (then killed if it lingers) when the block ends.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import httpx

PORT_PLACEHOLDER = "{port}"


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def serve_command(workers: int = 1) -> list[str]:
    """``edgepos serve`` on 127.0.0.1 with the port left as a placeholder."""
    return [
        sys.executable,
        "-m",
        "edgepos.cli",
        "serve",
        "--host",
        "127.0.0.1",
        "--port",
        PORT_PLACEHOLDER,
        "--workers",
        str(workers),
    ]


def clean_environment(**edgepos: str) -> dict[str, str]:
    """This process's environment without any EDGEPOS_* variable, plus ``edgepos``."""
    environment = {key: value for key, value in os.environ.items() if not key.startswith("EDGEPOS_")}
    environment.update(edgepos)
    return environment


@contextlib.contextmanager
def running(
    command: Sequence[str],
    environment: Mapping[str, str],
    log_path: Path,
    *,
    ready_timeout_s: float = 60.0,
) -> Iterator[str]:
    """Start ``command`` (``{port}`` replaced by a free port), wait until GET /readyz answers 200,
    and yield the base URL; stop the process afterwards."""
    port = free_port()
    argv = [part.replace(PORT_PLACEHOLDER, str(port)) for part in command]
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "wb") as log:
        process = subprocess.Popen(
            argv, env=dict(environment), stdout=log, stderr=subprocess.STDOUT, cwd=log_path.parent
        )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + ready_timeout_s
        while True:
            if process.poll() is not None:
                raise RuntimeError(f"{' '.join(argv)} exited early:\n{log_path.read_text()[-3000:]}")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                    break
            if time.monotonic() > deadline:
                raise RuntimeError(f"{' '.join(argv)} was not ready within {ready_timeout_s:g} s")
            time.sleep(0.1)
        yield url
    finally:
        process.terminate()
        try:
            process.wait(timeout=20.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def service_cpu_s(url: str, marker: bytes = b"serve") -> float:
    """CPU seconds (user + system) used so far by the ``edgepos serve`` process listening at ``url`` and
    its workers, from /proc (Linux): what a benchmark divides by the batches it sent. ``marker``: an
    argument of the server's command line, or a file name one ends with (another server, such as a
    benchmark's floor app, by its script's name)."""
    port = url.rsplit(":", 1)[1]
    stats = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmdline = (entry / "cmdline").read_bytes().split(b"\0")
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            stats[int(entry.name)] = (cmdline, int(fields[1]), int(fields[11]) + int(fields[12]))
    serve = [
        pid
        for pid, (cmdline, _, _) in stats.items()
        if any(part == marker or part.endswith(b"/" + marker) for part in cmdline)
        and port.encode() in cmdline
    ]
    family = set(serve)
    for pid, (_, parent, _) in stats.items():
        if parent in family:
            family.add(pid)
    return sum(stats[pid][2] for pid in family) / os.sysconf("SC_CLK_TCK")
