"""A store in Redis, shared by every worker of every replica (``redis://host:port/db``).

Each session is one Redis hash holding the record (the pipeline state as raw bytes, the last
batch's request hash and response for idempotent replay, and a ``version``). Writes are Lua
scripts, so each is atomic on the server whichever process sends it: an update replaces the hash
only if its ``version`` is still the one the writer read (compare-and-set), and refreshes the key's
TTL, so an idle session disappears by itself after ``ttl_s``. A sorted set of session ids scored by
``updated_at`` counts live sessions for the session limit without scanning the keyspace, and lets
expired entries be purged by score. RSUs live in one hash; the broadcast ephemerides in another
(digest, text and upload time, written in one transaction so a reader never sees a mix of two
uploads). Key layout and the durability of an acknowledged write under each persistence setting
are in docs/redis.md.

Every network failure or timeout surfaces as :class:`StoreUnavailable` after short, bounded
timeouts (one reconnect attempt), never as a hang.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import AsyncGenerator, AsyncIterator, Iterable, Mapping
from contextlib import asynccontextmanager
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from redis import exceptions as redis_errors
from redis.asyncio import BlockingConnectionPool, Redis
from redis.asyncio.retry import Retry
from redis.backoff import ExponentialBackoff
from redis.commands.core import AsyncScript

from edgepos.pipelines.base import NeighbourTrack, Rsu
from edgepos.store.base import (
    Clock,
    SessionRecord,
    SessionStore,
    StoredEphemerides,
    StoreUnavailable,
    TooManySessions,
    decode_track,
    encode_track,
)
from edgepos.store.ratelimit import SLACK_S, RateLimit

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
_CHUNK = 500

# Remove index entries scored below ARGV[1] (exclusive) and their session hashes (prefix ARGV[2]).
_PURGE = """
local function purge(index, cutoff, prefix)
  local stale = redis.call('ZRANGEBYSCORE', index, '-inf', '(' .. cutoff)
  for _, sid in ipairs(stale) do
    redis.call('DEL', prefix .. sid)
  end
  if #stale > 0 then
    redis.call('ZREMRANGEBYSCORE', index, '-inf', '(' .. cutoff)
  end
  return #stale
end
"""

# KEYS: session hash, index. ARGV: cutoff, session-key prefix, limit, ttl ms, score, id, fields...
_CREATE = (
    _PURGE
    + """
purge(KEYS[2], ARGV[1], ARGV[2])
if redis.call('EXISTS', KEYS[1]) == 1 then return -1 end
if redis.call('ZCARD', KEYS[2]) >= tonumber(ARGV[3]) then return -2 end
redis.call('HSET', KEYS[1], unpack(ARGV, 7))
redis.call('PEXPIRE', KEYS[1], ARGV[4])
redis.call('ZADD', KEYS[2], ARGV[5], ARGV[6])
return 1
"""
)

# KEYS: session hash, index. ARGV: expected version, ttl ms, score, id, fields...
_COMPARE_AND_SET = """
local version = redis.call('HGET', KEYS[1], 'version')
if (not version) or version ~= ARGV[1] then return 0 end
redis.call('DEL', KEYS[1])
redis.call('HSET', KEYS[1], unpack(ARGV, 5))
redis.call('PEXPIRE', KEYS[1], ARGV[2])
redis.call('ZADD', KEYS[2], ARGV[3], ARGV[4])
return 1
"""

# KEYS: index. ARGV: cutoff, session-key prefix. Returns {purged, remaining}.
_PURGE_AND_COUNT = (
    _PURGE
    + """
local purged = purge(KEYS[1], ARGV[1], ARGV[2])
return {purged, redis.call('ZCARD', KEYS[1])}
"""
)

# GCRA (edgepos.store.ratelimit.gcra, transcribed). KEYS: the key's TAT. ARGV: now, interval,
# tolerance, slack (s). Returns the wait in seconds as a string ("0" when allowed, and the TAT is stored
# with a TTL until the key's whole burst is back).
_TAKE_REQUEST = """
local now = tonumber(ARGV[1])
local tat = tonumber(redis.call('GET', KEYS[1]) or '')
if (not tat) or tat < now then tat = now end
local wait = tat - now - tonumber(ARGV[3])
if wait > tonumber(ARGV[4]) then return string.format('%.17g', wait) end
tat = tat + tonumber(ARGV[2])
redis.call('SET', KEYS[1], string.format('%.17g', tat), 'PX', math.ceil((tat - now) * 1000) + 1)
return '0'
"""

_UNAVAILABLE = (
    redis_errors.ConnectionError,  # refused, reset, DNS, auth failures, server still loading
    redis_errors.TimeoutError,
    redis_errors.ReadOnlyError,  # a replica after failover
    redis_errors.OutOfMemoryError,  # maxmemory reached under the noeviction policy
    redis_errors.ClusterDownError,
    redis_errors.TryAgainError,
    OSError,
    asyncio.TimeoutError,
)
_UNAVAILABLE_REPLIES = ("MISCONF", "LOADING", "MASTERDOWN", "NOREPLICAS", "BUSY")


def parse_url(url: str) -> tuple[str, str]:
    """Split ``redis://host:port/db?prefix=name:&socket_timeout=1`` into (client URL, key prefix).

    ``prefix`` is ours; every other query parameter is redis-py's. Connect and socket timeouts
    default to short values so that an unreachable server fails fast.
    """
    parts = urlsplit(url)
    if parts.scheme not in _SCHEMES:
        raise ValueError(f"not a Redis store URL (want redis://host:port/db): {url!r}")
    query = dict(parse_qsl(parts.query, keep_blank_values=True))
    prefix = query.pop("prefix", DEFAULT_PREFIX)
    if not prefix:
        raise ValueError("the Redis key prefix must not be empty")
    query.setdefault("socket_connect_timeout", str(DEFAULT_CONNECT_TIMEOUT_S))
    query.setdefault("socket_timeout", str(DEFAULT_SOCKET_TIMEOUT_S))
    query.setdefault("max_connections", str(DEFAULT_MAX_CONNECTIONS))
    query.setdefault("timeout", str(DEFAULT_POOL_TIMEOUT_S))
    return urlunsplit(parts._replace(query=urlencode(query))), prefix


def _pairs(record: SessionRecord, version: int) -> list[tuple[bytes, bytes]]:
    """The record's hash fields as bytes (absent optional values are left out)."""
    pairs: list[tuple[str, str | bytes]] = [
        ("vehicle_id", record.vehicle_id),
        ("pipeline", record.pipeline),
        ("options", json.dumps(record.options, allow_nan=False)),
        ("token_hash", record.token_hash),
        ("state", bytes(record.state)),
        ("created_at", repr(float(record.created_at))),
        ("updated_at", repr(float(record.updated_at))),
        ("last_seq", str(int(record.last_seq))),
        ("batches", str(int(record.batches))),
        ("epochs", str(int(record.epochs))),
        ("version", str(int(version))),
    ]
    optional = (
        ("last_request_hash", record.last_request_hash),
        ("last_response", None if record.last_response is None else bytes(record.last_response)),
        ("last_fix", record.last_fix),
    )
    pairs.extend((name, value) for name, value in optional if value is not None)
    return [(name.encode(), value if isinstance(value, bytes) else value.encode()) for name, value in pairs]


def _fields(record: SessionRecord, version: int) -> list[bytes]:
    """The record as a flat field/value list for HSET."""
    return [item for pair in _pairs(record, version) for item in pair]


def _record(session_id: str, raw: Mapping[bytes, bytes]) -> SessionRecord:
    """A record from the hash HGETALL returned (keys and values are bytes)."""
    text = {key.decode(): value for key, value in raw.items()}

    def optional_text(name: str) -> str | None:
        value = text.get(name)
        return None if value is None else value.decode()

    return SessionRecord(
        session_id=session_id,
        vehicle_id=text["vehicle_id"].decode(),
        pipeline=text["pipeline"].decode(),
        options=json.loads(text["options"]),
        token_hash=text["token_hash"].decode(),
        state=bytes(text["state"]),
        created_at=float(text["created_at"]),
        updated_at=float(text["updated_at"]),
        last_seq=int(text["last_seq"]),
        last_request_hash=optional_text("last_request_hash"),
        last_response=text.get("last_response"),
        batches=int(text["batches"]),
        epochs=int(text["epochs"]),
        last_fix=optional_text("last_fix"),
        version=int(text["version"]),
    )


def _rsu_value(rsu: Rsu) -> str:
    return json.dumps([rsu.x, rsu.y, rsu.range_std, rsu.bearing_std, rsu.radius])


def _rsu(rsu_id: str, value: bytes) -> Rsu:
    x, y, range_std, bearing_std, radius = json.loads(value)
    return Rsu(rsu_id, x, y, range_std, bearing_std, radius)


class RedisStore(SessionStore):
    """Sessions and RSUs in Redis under ``prefix`` (see docs/redis.md for the key layout)."""

    def __init__(self, url: str, ttl_s: float, clock: Clock = time.time) -> None:
        super().__init__(ttl_s, clock)
        self.url, self.prefix = parse_url(url)
        self.session_prefix = f"{self.prefix}session:"
        self.index_key = f"{self.prefix}sessions"
        self.rsu_key = f"{self.prefix}rsus"
        self.rate_prefix = f"{self.prefix}rate:"
        self.ephemerides_key = f"{self.prefix}ephemerides"
        self._ttl_ms = max(1, math.ceil(self.ttl_s * 1000.0))
        self._client: Redis | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closer: AsyncGenerator[None, None] | None = None
        self._scripts: dict[str, AsyncScript] = {}

    # plumbing -------------------------------------------------------------------------------
    async def _redis(self) -> Redis:
        """The client of the running event loop (asyncio connections belong to one loop)."""
        loop = asyncio.get_running_loop()
        if self._client is None or self._loop is not loop:
            # One reconnect attempt: replaces a pooled connection that went stale (Redis restarted)
            # and is safe for writes, which are compare-and-set or idempotent.
            pool = BlockingConnectionPool.from_url(
                self.url, retry=Retry(ExponentialBackoff(cap=0.2, base=0.05), retries=1)
            )
            client = Redis.from_pool(pool)  # closing the client closes its pool
            closer = self._closed_with_loop(client)
            self._client, self._loop, self._closer = client, loop, closer
            self._scripts = {
                "create": client.register_script(_CREATE),
                "cas": client.register_script(_COMPARE_AND_SET),
                "count": client.register_script(_PURGE_AND_COUNT),
                "take": client.register_script(_TAKE_REQUEST),
            }
            await anext(closer)  # started, so the loop's shutdown will close it
        return self._client

    @staticmethod
    async def _closed_with_loop(client: Redis) -> AsyncGenerator[None, None]:
        """Closes ``client`` when closed: by :meth:`close`, or by the event loop's shutdown
        (``asyncio.run`` closes every open async generator of its loop before closing the loop), so
        a store used from several short-lived loops leaves no socket behind."""
        try:
            yield
        finally:
            await client.aclose()

    @asynccontextmanager
    async def _guard(self) -> AsyncIterator[None]:
        """Turn every way Redis can fail to answer into StoreUnavailable."""
        try:
            yield
        except StoreUnavailable:
            raise
        except _UNAVAILABLE as error:
            raise StoreUnavailable(f"Redis does not answer: {error}") from error
        except redis_errors.ResponseError as error:
            if str(error).startswith(_UNAVAILABLE_REPLIES):
                raise StoreUnavailable(f"Redis refused the operation: {error}") from error
            raise

    def _session_key(self, session_id: str) -> str:
        return f"{self.session_prefix}{session_id}"

    def _cutoff(self) -> str:
        return repr(float(self.clock() - self.ttl_s))

    # sessions -------------------------------------------------------------------------------
    async def create(self, record: SessionRecord, max_sessions: int) -> None:
        key = self._session_key(record.session_id)
        async with self._guard():
            client = await self._redis()
            outcome = await self._scripts["create"](
                keys=[key, self.index_key],
                args=[
                    self._cutoff(),
                    self.session_prefix,
                    int(max_sessions),
                    self._ttl_ms,
                    repr(float(record.updated_at)),
                    record.session_id,
                    *_fields(record, record.version),
                ],
                client=client,
            )
            # A reconnect retry may resend a create that had already been applied: that one is ours.
            ours = outcome == -1 and await client.hgetall(key) == dict(_pairs(record, record.version))
        if outcome == -2:
            raise TooManySessions(max_sessions)
        if outcome == -1 and not ours:
            raise ValueError(f"session {record.session_id!r} already exists")

    async def get(self, session_id: str) -> SessionRecord | None:
        async with self._guard():
            raw = await (await self._redis()).hgetall(self._session_key(session_id))
        if not raw:
            return None
        record = _record(session_id, raw)
        return None if self.is_expired(record, self.clock()) else record

    async def compare_and_set(self, record: SessionRecord, expected_version: int) -> bool:
        async with self._guard():
            client = await self._redis()
            applied = await self._scripts["cas"](
                keys=[self._session_key(record.session_id), self.index_key],
                args=[
                    str(int(expected_version)),
                    self._ttl_ms,
                    repr(float(record.updated_at)),
                    record.session_id,
                    *_fields(record, expected_version + 1),
                ],
                client=client,
            )
        return applied == 1

    async def delete(self, session_id: str) -> bool:
        async with self._guard():
            async with (await self._redis()).pipeline(transaction=True) as pipe:
                pipe.delete(self._session_key(session_id))
                pipe.zrem(self.index_key, session_id)
                removed, _ = await pipe.execute()
        return bool(removed)

    async def _purge_and_count(self) -> tuple[int, int]:
        async with self._guard():
            client = await self._redis()
            purged, remaining = await self._scripts["count"](
                keys=[self.index_key], args=[self._cutoff(), self.session_prefix], client=client
            )
        return int(purged), int(remaining)

    async def count(self) -> int:
        return (await self._purge_and_count())[1]

    async def expire(self) -> int:
        return (await self._purge_and_count())[0]

    # RSUs -----------------------------------------------------------------------------------
    async def upsert_rsus(self, rsus: Iterable[Rsu]) -> int:
        mapping = {rsu.id: _rsu_value(rsu) for rsu in rsus}
        if not mapping:
            return 0
        items = list(mapping.items())
        async with self._guard():
            async with (await self._redis()).pipeline(transaction=True) as pipe:
                for start in range(0, len(items), _CHUNK):
                    pipe.hset(self.rsu_key, mapping=dict(items[start : start + _CHUNK]))
                await pipe.execute()
        return len(mapping)

    async def get_rsu(self, rsu_id: str) -> Rsu | None:
        return (await self.get_rsus([rsu_id])).get(rsu_id)

    async def get_rsus(self, rsu_ids: Iterable[str]) -> Mapping[str, Rsu]:
        wanted = sorted(set(rsu_ids))
        found: dict[str, Rsu] = {}
        async with self._guard():
            client = await self._redis()
            for start in range(0, len(wanted), _CHUNK):
                chunk = wanted[start : start + _CHUNK]
                values = await client.hmget(self.rsu_key, chunk)
                found.update({rid: _rsu(rid, value) for rid, value in zip(chunk, values) if value})
        return found

    async def list_rsus(self) -> list[Rsu]:
        async with self._guard():
            raw = await (await self._redis()).hgetall(self.rsu_key)
        rsus = [_rsu(key.decode(), value) for key, value in raw.items()]
        return sorted(rsus, key=lambda rsu: rsu.id)

    async def delete_rsu(self, rsu_id: str) -> bool:
        async with self._guard():
            return bool(await (await self._redis()).hdel(self.rsu_key, rsu_id))

    # broadcast ephemerides ------------------------------------------------------------------
    async def put_ephemerides(self, document: StoredEphemerides) -> None:
        async with self._guard():
            async with (await self._redis()).pipeline(transaction=True) as pipe:
                pipe.delete(self.ephemerides_key)
                pipe.hset(
                    self.ephemerides_key,
                    mapping={
                        "digest": document.digest,
                        "text": document.text.encode(),
                        "uploaded_at": repr(float(document.uploaded_at)),
                    },
                )
                await pipe.execute()

    async def get_ephemerides(self) -> StoredEphemerides | None:
        async with self._guard():
            raw = await (await self._redis()).hgetall(self.ephemerides_key)
        if not raw:
            return None
        return StoredEphemerides(
            digest=raw[b"digest"].decode(), text=raw[b"text"].decode(), uploaded_at=float(raw[b"uploaded_at"])
        )

    async def ephemerides_digest(self) -> str | None:
        async with self._guard():
            digest = await (await self._redis()).hget(self.ephemerides_key, "digest")
        return None if digest is None else bytes(digest).decode()

    async def delete_ephemerides(self) -> bool:
        async with self._guard():
            return bool(await (await self._redis()).delete(self.ephemerides_key))

    # neighbour tracks: one string key per vehicle, replaced whole by SET (atomic), expiring by itself
    def _track_key(self, vehicle_id: str) -> str:
        return f"{self.prefix}track:{vehicle_id}"

    async def put_track(self, track: NeighbourTrack) -> None:
        value = encode_track(track, self.clock())
        async with self._guard():
            await (await self._redis()).set(self._track_key(track.vehicle_id), value, px=self._ttl_ms)

    async def get_tracks(self, vehicle_ids: Iterable[str]) -> Mapping[str, NeighbourTrack]:
        wanted = sorted(set(vehicle_ids))
        found: dict[str, NeighbourTrack] = {}
        now = self.clock()
        async with self._guard():
            client = await self._redis()
            for start in range(0, len(wanted), _CHUNK):
                chunk = wanted[start : start + _CHUNK]
                values = await client.mget([self._track_key(vehicle) for vehicle in chunk])
                for vehicle, value in zip(chunk, values):
                    if value:
                        track, written_at = decode_track(vehicle, value)
                        if self.track_is_live(written_at, now):
                            found[vehicle] = track
        return found

    async def delete_track(self, vehicle_id: str) -> bool:
        async with self._guard():
            return bool(await (await self._redis()).delete(self._track_key(vehicle_id)))

    # request-rate limits --------------------------------------------------------------------
    async def take_request(self, key: str, limit: RateLimit) -> float:
        async with self._guard():
            client = await self._redis()
            wait = await self._scripts["take"](
                keys=[f"{self.rate_prefix}{key}"],
                args=[repr(float(self.clock())), repr(limit.interval_s), repr(limit.tolerance_s), repr(SLACK_S)],
                client=client,
            )
        return float(wait)

    # lifecycle ------------------------------------------------------------------------------
    async def ping(self) -> bool:
        async with self._guard():
            return bool(await (await self._redis()).ping())

    async def close(self) -> None:
        """Close this loop's connections; a later call reconnects."""
        closer, self._closer, self._client = self._closer, None, None
        if closer is not None and self._loop is asyncio.get_running_loop():
            await closer.aclose()
