"""Session and RSU stores: in-process (default) or one SQLite file shared by several workers."""

from __future__ import annotations

import time

from edgepos.store.base import Clock, SessionRecord, SessionStore, TooManySessions
from edgepos.store.memory import MemoryStore
from edgepos.store.sqlite import SQLiteStore, path_from_url

__all__ = ["MemoryStore", "SQLiteStore", "SessionRecord", "SessionStore", "TooManySessions", "open_store"]


def open_store(
    url: str, ttl_s: float, clock: Clock = time.time, *, wait_replicas: int = 0, wait_timeout_ms: int = 500
) -> SessionStore:
    """The store named by ``url``: ``memory``, ``sqlite:///path.db``, ``redis://...`` or
    ``redis-cluster://host:port[,host:port...]``; ``wait_replicas`` (Redis only) is how many replicas
    must hold a batch before it is acknowledged."""
    if wait_replicas and not url.startswith(("redis:", "rediss:", "unix:", "redis-cluster:")):
        raise ValueError("waiting for replicas needs a Redis store")
    if url == "memory":
        return MemoryStore(ttl_s, clock)
    if url.startswith("sqlite:"):
        return SQLiteStore(path_from_url(url), ttl_s, clock)
    if url.startswith("redis-cluster:"):
        from edgepos.store.redis_cluster import RedisClusterStore

        return RedisClusterStore(
            url, ttl_s, clock, wait_replicas=wait_replicas, wait_timeout_ms=wait_timeout_ms
        )
    if url.startswith(("redis:", "rediss:", "unix:")):
        from edgepos.store.redis import RedisStore  # redis-py is only imported when configured

        return RedisStore(url, ttl_s, clock, wait_replicas=wait_replicas, wait_timeout_ms=wait_timeout_ms)
    raise ValueError(
        f"unknown store {url!r}: use 'memory', 'sqlite:///path.db', 'redis://host:port/db' or "
        "'redis-cluster://host:port[,host:port...]'"
    )
