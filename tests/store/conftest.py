"""Real redis-server processes for the store tests (single servers and a six-node Redis Cluster):
loopback only, each in its own temporary directory, on a free port. Skipped (with the reason) only
when the redis-server or redis-cli binary is absent."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from edgepos.loadgen.localredis import (
    RedisClusterProcesses,
    RedisServer,
    free_port,
    redis_binary,
    redis_cli_binary,
)

__all__ = ["RedisClusterProcesses", "RedisServer", "free_port"]


def _binary() -> str:
    binary = redis_binary()
    if binary is None:
        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    return binary


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    """One shared in-memory redis-server (no persistence); tests keep apart by key prefix."""
    server = RedisServer(_binary(), tmp_path_factory.mktemp("redis"), "--save", "", "--appendonly", "no")
    server.start()
    yield server
    server.stop()


@pytest.fixture
def redis_factory(tmp_path: Path) -> Iterator[Callable[..., RedisServer]]:
    """Builds extra servers with their own config (``factory(*config)``); all stopped afterwards."""
    binary = _binary()
    servers: list[RedisServer] = []

    def make(*config: str) -> RedisServer:
        server = RedisServer(binary, tmp_path / f"redis-{len(servers)}", *config)
        servers.append(server)
        return server

    yield make
    for server in servers:
        server.stop()


def _cli() -> None:
    if redis_cli_binary() is None:
        pytest.skip("redis-cli is not installed (apt-get install -y redis-tools)")


@pytest.fixture(scope="session")
def redis_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisClusterProcesses]:
    """One shared Redis Cluster of three primaries and three replicas on loopback (no persistence);
    tests keep apart by key prefix. Tests that kill or reshard nodes build their own."""
    binary = _binary()
    _cli()
    cluster = RedisClusterProcesses(
        binary, tmp_path_factory.mktemp("redis-cluster"), "--save", "", "--appendonly", "no"
    )
    cluster.start()
    yield cluster
    cluster.stop()
