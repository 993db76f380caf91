"""Fault tests run real processes (redis-server, edgepos serve) on loopback; they need redis-server."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from edgepos.loadgen.localredis import RedisServer


@pytest.fixture
def redis_factory(tmp_path: Path) -> Iterator[Callable[..., RedisServer]]:
    """Builds (unstarted) redis-servers with their own config; all stopped afterwards."""
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    servers: list[RedisServer] = []

    def make(*config: str) -> RedisServer:
        server = RedisServer(binary, tmp_path / f"redis-{len(servers)}", *config)
        servers.append(server)
        return server

    yield make
    for server in servers:
        server.stop()
