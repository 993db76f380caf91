"""Fault tests run real processes (redis-server, edgepos serve) on loopback; they need redis-server."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from edgepos.loadgen.localredis import RedisClusterProcesses, RedisServer


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


@pytest.fixture
def cluster_factory(tmp_path: Path) -> Iterator[Callable[..., RedisClusterProcesses]]:
    """Builds (unstarted) local Redis Clusters, three primaries and three replicas; all stopped afterwards."""
    binary = shutil.which("redis-server")
    if binary is None or shutil.which("redis-cli") is None:
        pytest.skip("redis-server and redis-cli are not installed (apt-get install -y redis-server)")
    clusters: list[RedisClusterProcesses] = []

    def make(*config: str) -> RedisClusterProcesses:
        cluster = RedisClusterProcesses(binary, tmp_path / f"cluster-{len(clusters)}", *config)
        clusters.append(cluster)
        return cluster

    yield make
    for cluster in clusters:
        cluster.stop()
