"""The Redis store's URL: ``redis://host:port/db?prefix=name:&record_cache=2048&socket_timeout=1``, with the
short timeouts and the bounded pool the store defaults to."""

from __future__ import annotations

from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from edgepos.store.redis_cache import DEFAULT_RECORD_CACHE

DEFAULT_PREFIX = "edgepos:"
DEFAULT_CONNECT_TIMEOUT_S = 0.5
DEFAULT_SOCKET_TIMEOUT_S = 1.0
DEFAULT_MAX_CONNECTIONS = 64
"""Connections per worker process. Requests beyond it wait for a free connection (a Redis
command takes well under a millisecond) instead of opening more: a thousand vehicles connecting at
once would otherwise open a thousand sockets, miss the connect timeout and answer 503."""
DEFAULT_POOL_TIMEOUT_S = 5.0
"""How long a request waits for a pooled connection before answering 503."""
_SCHEMES = ("redis", "rediss", "unix")


def take_record_cache(url: str) -> tuple[str, int]:
    """The URL without our ``record_cache`` parameter (the session records a worker keeps, see
    store.redis_cache; default 2048, 0: none), and its value."""
    parts = urlsplit(url)
    query = dict(parse_qsl(parts.query, keep_blank_values=True))
    text = query.pop("record_cache", None)
    try:
        size = DEFAULT_RECORD_CACHE if text is None else int(text)
    except ValueError:
        raise ValueError(
            f"record_cache in the Redis store URL must be a whole number, got {text!r}"
        ) from None
    if size < 0:
        raise ValueError(f"record_cache in the Redis store URL must be >= 0, got {size}")
    return urlunsplit(parts._replace(query=urlencode(query))), size


def parse_url(url: str) -> tuple[str, str]:
    """Split ``redis://host:port/db?prefix=name:&socket_timeout=1`` into (client URL, key prefix).

    ``prefix`` and ``record_cache`` are ours; every other query parameter is redis-py's. Connect and
    socket timeouts default to short values so that an unreachable server fails fast.
    """
    parts = urlsplit(url)
    if parts.scheme not in _SCHEMES:
        raise ValueError(f"not a Redis store URL (want redis://host:port/db): {url!r}")
    query = dict(parse_qsl(parts.query, keep_blank_values=True))
    query.pop("record_cache", None)
    prefix = query.pop("prefix", DEFAULT_PREFIX)
    if not prefix:
        raise ValueError("the Redis key prefix must not be empty")
    query.setdefault("socket_connect_timeout", str(DEFAULT_CONNECT_TIMEOUT_S))
    query.setdefault("socket_timeout", str(DEFAULT_SOCKET_TIMEOUT_S))
    query.setdefault("max_connections", str(DEFAULT_MAX_CONNECTIONS))
    query.setdefault("timeout", str(DEFAULT_POOL_TIMEOUT_S))
    return urlunsplit(parts._replace(query=urlencode(query))), prefix
