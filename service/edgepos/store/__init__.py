"""Session and RSU stores: in-process (default) or one SQLite file shared by several workers."""

from __future__ import annotations

import time

from edgepos.store.base import Clock, SessionRecord, SessionStore, TooManySessions
from edgepos.store.memory import MemoryStore
from edgepos.store.sqlite import SQLiteStore, path_from_url

__all__ = ["MemoryStore", "SQLiteStore", "SessionRecord", "SessionStore", "TooManySessions", "open_store"]


def open_store(url: str, ttl_s: float, clock: Clock = time.time) -> SessionStore:
    """The store named by ``url``: ``memory`` or ``sqlite:///path.db``."""
    if url == "memory":
        return MemoryStore(ttl_s, clock)
    if url.startswith("sqlite:"):
        return SQLiteStore(path_from_url(url), ttl_s, clock)
    if url.startswith(("redis:", "rediss:", "unix:")):
        from edgepos.store.redis import RedisStore  # redis-py is only imported when configured

        return RedisStore(url, ttl_s, clock)
    raise ValueError(f"unknown store {url!r}: use 'memory', 'sqlite:///path.db' or 'redis://host:port/db'")
