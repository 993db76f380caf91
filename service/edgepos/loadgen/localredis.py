"""Run a ``redis-server`` on a free loopback port, in its own data directory, and restart or kill it.

Used by the Redis store's tests, the fault tests and the Redis benchmarks (never by the service
itself). Loopback only; the caller chooses persistence through ``redis-server`` options.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

START_TIMEOUT_S = 10.0


def free_port() -> int:
    """A loopback TCP port nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def redis_binary() -> str | None:
    """The ``redis-server`` on PATH, or None."""
    return shutil.which("redis-server")


class RedisServer:
    """One redis-server on 127.0.0.1:``port`` with its data in ``directory``; restartable on the
    same port and directory (so an append-only file or snapshot is read back)."""

    def __init__(self, binary: str, directory: Path, *config: str) -> None:
        self.binary = binary
        self.directory = directory
        self.port = free_port()
        self.config = config
        self.process: subprocess.Popen[bytes] | None = None

    def url(self, prefix: str = "", **query: str) -> str:
        params = {"prefix": prefix, **query} if prefix else dict(query)
        tail = "&".join(f"{key}={value}" for key, value in params.items())
        return f"redis://127.0.0.1:{self.port}/0" + (f"?{tail}" if tail else "")

    def start(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        command = [
            self.binary,
            "--port", str(self.port),
            "--bind", "127.0.0.1",
            "--dir", str(self.directory),
            "--daemonize", "no",
            "--logfile", "redis.log",
            *self.config,
        ]  # fmt: skip
        self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                log = (self.directory / "redis.log").read_text(errors="replace")[-2000:]
                raise RuntimeError(f"redis-server exited with {self.process.returncode}: {log}")
            if self.command("PING") == b"+PONG\r\n":
                return
            time.sleep(0.02)
        self.stop()
        raise RuntimeError(f"redis-server did not answer on port {self.port} within {START_TIMEOUT_S} s")

    def command(self, *words: str) -> bytes:
        """Send one inline command and return the raw reply (b'' if nobody answers)."""
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=1.0) as conn:
                conn.sendall((" ".join(words) + "\r\n").encode())
                return conn.recv(65536)
        except OSError:
            return b""

    def kill(self) -> None:
        """SIGKILL: no shutdown save, no final AOF flush beyond what Redis already wrote."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        self.process = None

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
        self.process = None

    def __enter__(self) -> RedisServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
