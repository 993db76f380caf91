"""A store in Redis, shared by every worker of every replica (``redis://host:port/db``).

Each session is one Redis hash holding the record (the pipeline state as raw bytes, the last
batch's request hash and response for idempotent replay, and a ``version``). Writes are Lua
scripts, so each is atomic on the server whichever process sends it: an update replaces the hash
only if its ``version`` is still the one the writer read (compare-and-set), and refreshes the key's
TTL, so an idle session disappears by itself after ``ttl_s``. A sorted set of session ids scored by
``updated_at`` counts live sessions for the session limit without scanning the keyspace, and lets
expired entries be purged by score. RSUs live in one hash; the broadcast ephemerides in another
(digest, text and upload time, written in one transaction so a reader never sees a mix of two
uploads). Registered vehicles live in one hash with a second hash indexing them by key hash; each
vehicle's live session is named by a pointer key that carries its session's TTL. Every write that
touches several keys (creating a session, which may supersede the vehicle's previous one; deleting
a session; publishing a track; registering, re-keying or revoking vehicles) is one Lua script. Key
layout and the durability of an acknowledged write under each persistence setting are in
docs/redis.md.

Every network failure or timeout surfaces as :class:`StoreUnavailable` after short, bounded
timeouts (one reconnect attempt), never as a hang.
"""

from __future__ import annotations

import asyncio
import math
import secrets
import time
from collections.abc import AsyncGenerator, AsyncIterator, Iterable, Mapping, Sequence
from contextlib import asynccontextmanager
from typing import Any
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from redis import exceptions as redis_errors
from redis.asyncio import BlockingConnectionPool, Redis
from redis.asyncio.retry import Retry
from redis.backoff import ExponentialBackoff
from redis.commands.core import AsyncScript

from edgepos.pipelines.base import NeighbourTrack
from edgepos.store import redis_scripts as scripts
from edgepos.store.base import (
    Clock,
    NotReplicated,
    Revocation,
    SessionRecord,
    SessionStore,
    SessionSummary,
    StoreUnavailable,
    Supersession,
    TooManySessions,
    VehicleNotRegistered,
    decode_track,
    encode_track,
    refuse_fixes_in_write,
)
from edgepos.store.fixlog import FixLog, NewFix
from edgepos.store.ratelimit import SLACK_S, RateLimit, gcra
from edgepos.store.redis_base import RedisBaseStations
from edgepos.store.redis_cache import RSUS_USED, RecordCache, RsuSnapshot
from edgepos.store.redis_fix_entries import fix_arguments
from edgepos.store.redis_packing import PACKED
from edgepos.store.redis_records import (
    RECORD_FIELDS,
    SUMMARY_FIELDS,
    record_fields,
    record_from_hash,
    record_pairs,
    summary_from_fields,
)
from edgepos.store.redis_registry import RedisRegistry
from edgepos.store.redis_round_trip import Command, RoundTrips, allow_for_wait
from edgepos.store.redis_url import DEFAULT_SOCKET_TIMEOUT_S, parse_url, take_record_cache

_CHUNK = 500

_UNAVAILABLE = (
    redis_errors.ConnectionError,  # refused, reset, DNS, auth failures, server still loading
    redis_errors.TimeoutError,
    redis_errors.ReadOnlyError,  # a replica after failover
    redis_errors.OutOfMemoryError,  # maxmemory reached under the noeviction policy
    redis_errors.ClusterDownError,
    redis_errors.TryAgainError,
    redis_errors.SlotNotCoveredError,  # Redis Cluster: a slot without a primary (failover under way)
    redis_errors.ClusterError,  # Redis Cluster: redirections or topology refreshes ran out of retries
    OSError,
    asyncio.TimeoutError,
)
_UNAVAILABLE_REPLIES = ("MISCONF", "LOADING", "MASTERDOWN", "NOREPLICAS", "BUSY", "CLUSTERDOWN", "TRYAGAIN")


RSUS_CHANGED = -2
"""The compare-and-set's answer when the RSU map's token is not the one the batch was computed on."""
_DISCARD_GRACE_S = 5.0
STAGED_TTL_MS = 60_000
"""How long a staged session record outlives a lost connection (the compare-and-set renames or drops it
in the same round trip otherwise)."""


def _leaked_transport_error(error: BaseException) -> bool:
    """Whether ``error`` was raised writing to a closed socket inside redis-py (see ``_guard``)."""
    frame = error.__traceback__
    while frame is not None:
        if frame.tb_frame.f_code.co_filename.endswith(
            ("redis/asyncio/connection.py", "redis/asyncio/cluster.py", "edgepos/store/redis_packing.py")
        ):
            return True
        frame = frame.tb_next
    return False


class RedisStore(RedisRegistry, RedisBaseStations, SessionStore):
    """Sessions and RSUs in Redis under ``prefix`` (see docs/redis.md for the key layout)."""

    SCRIPTS: Mapping[str, str] = {
        "create": scripts.CREATE,
        "cas": scripts.COMPARE_AND_RENAME,
        "cas_fixes": scripts.COMPARE_AND_RENAME_PUBLISHING,
        "count": scripts.PURGE_AND_COUNT,
        "take": scripts.TAKE_REQUEST,
        "delete": scripts.DELETE,
        "put_track": scripts.PUT_TRACK,
        "add_vehicles": scripts.ADD_VEHICLES,
        "rotate": scripts.ROTATE_VEHICLE_KEY,
        "delete_vehicle": scripts.DELETE_VEHICLE,
        "publish_fixes": scripts.PUBLISH_FIXES,
        "replace_document": scripts.REPLACE_DOCUMENT,
        "acquire_lease": scripts.ACQUIRE_LEASE,
        "add_base_epochs": scripts.ADD_BASE_EPOCHS,
        "replace_base_station": scripts.REPLACE_BASE_STATION,
    }

    def __init__(
        self,
        url: str,
        ttl_s: float,
        clock: Clock = time.time,
        *,
        wait_replicas: int = 0,
        wait_timeout_ms: int = 500,
    ) -> None:
        super().__init__(ttl_s, clock)
        url, record_cache = take_record_cache(url)
        self.url, self.prefix = self._parse_url(url)
        # one round trip per batch (store.redis_cache): the records this worker wrote, the RSU map it read
        self.records = RecordCache(record_cache)
        self.cache_rsus = True
        self._rsus: RsuSnapshot | None = None
        # WAIT: a batch is acknowledged only once this many replicas have it (0: once the primary has it)
        self.wait_replicas, self.wait_timeout_ms = int(wait_replicas), int(wait_timeout_ms)
        self.durable_key = f"{self.prefix}durable"
        self.session_prefix = f"{self.prefix}session:"
        self.index_key = f"{self.prefix}sessions"
        self.rsu_key = f"{self.prefix}rsus"
        self.rsu_token_key = f"{self.prefix}rsus:token"
        self.rate_prefix = f"{self.prefix}rate:"
        self.ephemerides_key = f"{self.prefix}ephemerides"
        self.documents_prefix = f"{self.prefix}documents:"
        self.lease_prefix = f"{self.prefix}lease:"
        self.vehicles_key = f"{self.prefix}vehicles"
        self.vehicle_keys_key = f"{self.prefix}vehiclekeys"
        self.live_prefix = f"{self.prefix}live:"
        self.superseded_prefix = f"{self.prefix}superseded:"
        self.track_prefix = f"{self.prefix}track:"
        # the fix stream and its id counter: one hash tag, so one slot on a Redis Cluster
        self.fixes_key = f"{self.prefix}{{fixes}}:entries"
        self.fixes_seq_key = f"{self.prefix}{{fixes}}:seq"
        self._ttl_ms = max(1, math.ceil(self.ttl_s * 1000.0))
        self._client: Any = None  # redis.asyncio.Redis, or RedisCluster in the cluster store
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closer: AsyncGenerator[None, None] | None = None
        self._fix_buffer = 0  # the fixes the fix stream holds, once its log is made (fix_log)
        self._trips = RoundTrips()  # on the newest pool's connections, kept between round trips
        self._scripts: dict[str, AsyncScript] = {}
        self._closing: set[asyncio.Task[None]] = set()  # clients discarded, closing after their grace period

    # plumbing -------------------------------------------------------------------------------
    @staticmethod
    def _parse_url(url: str) -> tuple[str, str]:
        return parse_url(url)

    async def _redis(self) -> Any:
        """The client of the running event loop (asyncio connections belong to one loop)."""
        loop = asyncio.get_running_loop()
        if self._client is None or self._loop is not loop:
            client = self._connect()
            closer = self._closed_with_loop(client)
            self._client, self._loop, self._closer = client, loop, closer
            self._scripts = {name: client.register_script(source) for name, source in self.SCRIPTS.items()}
            await anext(closer)  # started, so the loop's shutdown will close it
        return self._client

    def _connect(self) -> Any:
        """A new client with its own connection pool."""
        # One reconnect attempt: replaces a pooled connection that went stale (Redis restarted)
        # and is safe for writes, which are compare-and-set or idempotent.
        pool = BlockingConnectionPool.from_url(
            self.url, retry=Retry(ExponentialBackoff(cap=0.2, base=0.05), retries=1)
        )
        allow_for_wait(pool.connection_kwargs, self.wait_timeout_ms if self.wait_replicas else 0)
        self._trips.keep_from(pool)
        # the class the URL's scheme chose, packing commands in C (store.redis_packing)
        pool.connection_class = PACKED.get(pool.connection_class, pool.connection_class)
        return Redis.from_pool(pool)  # closing the client closes its pool

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
        except (RuntimeError, AttributeError, TypeError) as error:
            if not _leaked_transport_error(error):
                raise
            # redis-py 8 lets a write on a connection the server reset escape as the transport's own
            # error (redis/redis-py#4287) and keeps that connection pooled: answer 503 and start
            # afresh with new connections (the old client is closed once its requests are done).
            self._discard_client()
            raise StoreUnavailable(f"Redis dropped the connection: {error!r}") from error

    def _discard_client(self) -> None:
        """Forget this loop's client (the next operation connects anew); close it after a grace period."""
        closer, self._client, self._closer = self._closer, None, None
        if closer is None:
            return

        async def close_later() -> None:
            await asyncio.sleep(_DISCARD_GRACE_S)
            await closer.aclose()

        task = asyncio.get_running_loop().create_task(close_later())
        self._closing.add(task)
        task.add_done_callback(self._closing.discard)

    # key names: one place, so that a cluster store can put a session's keys in one hash slot
    def _session_prefix_of(self, session_id: str) -> str:
        """The prefix of the session keys stored beside ``session_id``'s (the purge scripts build names from it)."""
        return self.session_prefix

    def _session_key(self, session_id: str) -> str:
        return f"{self._session_prefix_of(session_id)}{session_id}"

    def _index_key(self, session_id: str) -> str:
        """The sorted set of live sessions that ``session_id`` is counted in."""
        return self.index_key

    def _superseded_key(self, session_id: str) -> str:
        return f"{self.superseded_prefix}{session_id}"

    def _registry_key_for_create(self, session_id: str) -> str:
        """The vehicle registry as the create script reads it (it checks the vehicle's key there)."""
        return self.vehicles_key

    def _live_key(self, vehicle_id: str, session_id: str | None = None) -> str:
        """The vehicle's live-session pointer (with ``session_id`` given: beside that session's keys)."""
        return f"{self.live_prefix}{vehicle_id}"

    def _cutoff(self) -> str:
        return repr(float(self.clock() - self.ttl_s))

    # sessions -------------------------------------------------------------------------------
    async def create(
        self, record: SessionRecord, max_sessions: int, *, vehicle_key_hash: str | None = None
    ) -> str | None:
        key = self._session_key(record.session_id)
        async with self._guard():
            client = await self._redis()
            outcome = await self._scripts["create"](
                keys=[
                    key,
                    self._index_key(record.session_id),
                    self._registry_key_for_create(record.session_id),
                    self._live_key(record.vehicle_id),
                    self._track_key(record.vehicle_id),
                ],
                args=[
                    self._cutoff(),
                    self._session_prefix_of(record.session_id),
                    int(max_sessions),
                    self._ttl_ms,
                    repr(float(record.updated_at)),
                    record.session_id,
                    record.vehicle_id,
                    "" if vehicle_key_hash is None else vehicle_key_hash,
                    self._superseded_key(record.session_id)[: -len(record.session_id)],
                    repr(float(self.clock())),
                    *record_fields(record, record.version),
                ],
                client=client,
            )
            code = int(outcome[0])
            # A reconnect retry may resend a create that had already been applied: that one is ours
            # (which session it superseded, if any, is then not known any more).
            ours = code == -1 and await client.hgetall(key) == dict(record_pairs(record, record.version))
        if code == -3:
            raise VehicleNotRegistered(record.vehicle_id)
        if code == -2:
            raise TooManySessions(max_sessions)
        if code == -1:
            if ours:
                return None
            raise ValueError(f"session {record.session_id!r} already exists")
        self.records.put(record, record.version)
        superseded = bytes(outcome[1]).decode()
        if superseded:
            self.records.drop(superseded)
        return superseded or None

    async def live_session(self, vehicle_id: str) -> str | None:
        async with self._guard():
            client = await self._redis()
            pointer = await client.get(self._live_key(vehicle_id))
            if pointer is None:
                return None
            session_id = bytes(pointer).decode()
            updated = await client.hget(self._session_key(session_id), "updated_at")
        if updated is None or self.clock() - float(updated) > self.ttl_s:
            return None
        return session_id

    async def supersession(self, session_id: str) -> Supersession | None:
        async with self._guard():
            client = await self._redis()
            by, token_hash, at = await client.hmget(
                self._superseded_key(session_id), ["superseded_by", "token_hash", "at"]
            )
        if by is None or token_hash is None or at is None or self.clock() - float(at) > self.ttl_s:
            return None
        return Supersession(session_id, bytes(by).decode(), bytes(token_hash).decode(), float(at))

    async def list_sessions(
        self,
        *,
        after: str | None = None,
        limit: int = 100,
        pipeline: str | None = None,
        vehicle_id: str | None = None,
    ) -> list[SessionSummary]:
        if limit <= 0:
            return []
        found: list[SessionSummary] = []
        now = self.clock()
        async with self._guard():
            client = await self._redis()
            if vehicle_id is not None:  # a vehicle has at most one session: its live one
                pointer = await client.get(self._live_key(vehicle_id))
                candidates = [] if pointer is None else [bytes(pointer).decode()]
            else:
                candidates = sorted(await self._indexed_session_ids(client))
            if after is not None:
                candidates = [sid for sid in candidates if sid > after]
            step = max(limit, 50)
            for start in range(0, len(candidates), step):
                chunk = candidates[start : start + step]
                async with client.pipeline(transaction=False) as pipe:
                    for sid in chunk:
                        pipe.hmget(self._session_key(sid), list(SUMMARY_FIELDS))
                    replies = await pipe.execute()
                for sid, values in zip(chunk, replies):
                    summary = summary_from_fields(sid, values)
                    if summary is None or now - summary.updated_at > self.ttl_s:
                        continue  # vanished or expired since the index was read
                    if pipeline is not None and summary.pipeline != pipeline:
                        continue
                    if vehicle_id is not None and summary.vehicle_id != vehicle_id:
                        continue
                    found.append(summary)
                    if len(found) >= limit:
                        return found
        return found

    async def _indexed_session_ids(self, client: Any) -> list[str]:
        """The ids in the session index scored after the TTL cutoff (expired ones not purged yet left out)."""
        members = await client.zrangebyscore(self.index_key, self._cutoff(), "+inf")
        return [bytes(member).decode() for member in members]

    async def get(self, session_id: str, *, with_response: bool = True) -> SessionRecord | None:
        async with self._guard():
            client = await self._redis()
            key = self._session_key(session_id)
            if with_response:
                raw = await client.hgetall(key)
            else:
                values = await client.hmget(key, RECORD_FIELDS)
                raw = {
                    name.encode(): value for name, value in zip(RECORD_FIELDS, values) if value is not None
                }
        if not raw:
            return None
        record = record_from_hash(session_id, raw)
        return None if self.is_expired(record, self.clock()) else record

    async def get_for_batch(self, session_id: str) -> SessionRecord | None:
        """The record this worker wrote last for the session, if it has it and it is not expired by its
        ``updated_at``; else a read. The batch's compare-and-set refuses a stale one (store.redis_cache)."""
        RSUS_USED.set(None)  # a new batch (a WebSocket's frames share one task): no RSU map used yet
        record = self.records.get(session_id)
        if record is not None and not self.is_expired(record, self.clock()):
            return record
        self.records.drop(session_id)
        return await self.get(session_id, with_response=False)

    APPENDS_FIXES_IN_WRITE = True
    """The fix stream shares the server with the sessions: a batch's fix events go in its write's script."""

    async def compare_and_set(
        self, record: SessionRecord, expected_version: int, fixes: Sequence[NewFix] = ()
    ) -> bool:
        if not self.fixes_in_write:
            refuse_fixes_in_write(fixes)
        # the token of the RSU map this request's batch was computed on, if it used this worker's copy
        rsus_used = RSUS_USED.get()
        RSUS_USED.set(None)
        session_key = self._session_key(record.session_id)
        keys = [
            session_key,
            self._index_key(record.session_id),
            self._live_key(record.vehicle_id, record.session_id),
            # beside the session's key (its hash slot on a cluster), unique to this attempt
            f"{session_key}:staged:{secrets.token_hex(8)}",
        ]
        args: list[bytes | str | int] = [
            str(int(expected_version)),
            self._ttl_ms,
            repr(float(record.updated_at)),
            record.session_id,
        ]
        script = "cas_fixes" if fixes else "cas"
        if fixes:  # the stream, its counter, then the token key if any (the script's layout)
            keys += [self.fixes_key, self.fixes_seq_key]
            args += [rsus_used or "", self._fix_buffer, *fix_arguments(fixes)]
        if rsus_used is not None:
            keys.append(self.rsu_token_key)
            if not fixes:
                args.append(rsus_used)
        fields = record_fields(record, expected_version + 1)
        try:
            async with self._guard():
                client = await self._redis()
                applied, replicas = await self._staged_write(client, keys, args, fields, script)
        except BaseException:
            self.records.drop(record.session_id)  # whether it was written is not known
            raise
        if applied == 1:
            self.records.put(record, expected_version + 1)
        elif applied == RSUS_CHANGED:
            self.forget_rsus()  # the session is as cached; the batch is redone on the new map
        else:
            self.records.drop(record.session_id)
        if applied == -1:
            raise StoreUnavailable("Redis did not take the session's new record; send the same batch again")
        if applied == 1 and self.wait_replicas:
            self._check_replicas(replicas, "the batch")
        return applied == 1

    async def _staged_write(
        self, client: Any, keys: list[str], args: list[bytes | str | int], fields: list[bytes], script: str
    ) -> tuple[int, int]:
        """The new record as a staged hash, then the compare-and-rename ``script``, in one pipeline (one round
        trip); with ``wait_replicas``, WAIT on the same connection: (applied, replicas that have it)."""
        replies = await self._staged_pipeline(
            client, keys, args, fields, script, wait=bool(self.wait_replicas)
        )
        return int(replies[2]), int(replies[3]) if self.wait_replicas else 0

    async def _staged_pipeline(
        self,
        client: Any,
        keys: list[str],
        args: list[bytes | str | int],
        fields: list[bytes],
        name: str,
        *,
        wait: bool,
    ) -> list[Any]:
        """Sends HSET staged, PEXPIRE staged (a staged hash orphaned by a lost connection goes by itself),
        EVALSHA compare-and-rename and, with ``wait``, WAIT; the replies. The script is sent by its digest
        (redis-py's pipelined scripts would ask SCRIPT EXISTS first: a second round trip per batch) and
        loaded again only if the server lost it (restart, SCRIPT FLUSH)."""
        script = self._scripts[name]
        commands: list[Command] = [
            ("HSET", keys[3], *fields),
            ("PEXPIRE", keys[3], STAGED_TTL_MS),
            ("EVALSHA", script.sha, len(keys), *keys, *args),
        ]
        if wait:
            commands.append(("WAIT", self.wait_replicas, self.wait_timeout_ms))
        for _attempt in range(2):
            replies = await self._round_trip(client, commands)
            if isinstance(replies[2], redis_errors.NoScriptError):
                await client.script_load(script.script)
                continue
            for reply in replies:
                if isinstance(reply, Exception):
                    raise reply
            return replies
        raise StoreUnavailable("Redis kept losing the compare-and-set script; send the same batch again")

    async def _round_trip(self, client: Any, commands: list[Command]) -> list[Any]:
        """``commands`` in one write on one pooled connection, their replies (an error reply in its place)."""
        return await self._trips.run(client, commands)

    async def _evalsha(self, client: Any, name: str, keys: list[str], args: list[Any]) -> Any:
        """The reply of the script ``name`` (for the calls of every batch: the fix stream's append, the rate
        limit's budget), in one round trip of store.redis_round_trip."""
        script = self._scripts[name]
        return await self._trips.evalsha(client, script.sha, script.script, keys, args)

    async def make_durable(self, session_id: str) -> None:
        """A write of this connection's own, then WAIT: the replication stream is ordered, so once the
        replicas have that write they have every write acknowledged before it."""
        if not self.wait_replicas:
            return
        async with self._guard():
            client = await self._redis()
            pipe = client.pipeline(transaction=False)
            pipe.set(self.durable_key, b"1")
            pipe.execute_command("WAIT", self.wait_replicas, self.wait_timeout_ms)
            _, replicas = await pipe.execute()
        self._check_replicas(int(replicas), "the stored answer")

    def _check_replicas(self, replicas: int, what: str) -> None:
        if replicas < self.wait_replicas:
            raise NotReplicated(
                f"{what} reached {replicas} of the {self.wait_replicas} replica(s) it must reach within "
                f"{self.wait_timeout_ms} ms (EDGEPOS_REDIS_WAIT_REPLICAS); it is not acknowledged: send the same "
                "batch again"
            )

    async def delete(self, session_id: str) -> bool:
        self.records.drop(session_id)
        async with self._guard():
            client = await self._redis()
            removed = await self._scripts["delete"](
                keys=[self._session_key(session_id), self._index_key(session_id)],
                args=[session_id, self._live_key("", session_id), self._track_key("", session_id)],
                client=client,
            )
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
        # Supersession records and live pointers carry TTLs of their own: Redis drops them.
        return (await self._purge_and_count())[0]

    # vehicle registry: the rest is in store/redis_registry.py ---------------------------
    async def delete_vehicle(self, vehicle_id: str) -> Revocation | None:
        async with self._guard():
            client = await self._redis()
            outcome = await self._scripts["delete_vehicle"](
                keys=[
                    self.vehicles_key,
                    self.vehicle_keys_key,
                    self._live_key(vehicle_id),
                    self._track_key(vehicle_id),
                    self.index_key,
                ],
                args=[vehicle_id, self.session_prefix, self._cutoff()],
                client=client,
            )
        if int(outcome[0]) == 0:
            return None
        ended = bytes(outcome[1]).decode()
        self.records.drop(ended)
        return Revocation(vehicle_id, ended or None)

    # neighbour tracks: one string key per vehicle, replaced whole by SET (atomic), expiring by itself
    def _track_key(self, vehicle_id: str, session_id: str | None = None) -> str:
        return f"{self.track_prefix}{vehicle_id}"

    async def put_track(self, track: NeighbourTrack, session_id: str) -> bool:
        now = self.clock()
        async with self._guard():
            client = await self._redis()
            written = await self._scripts["put_track"](
                keys=[
                    self._live_key(track.vehicle_id, session_id),
                    self._session_key(session_id),
                    self._index_key(session_id),
                    self._track_key(track.vehicle_id, session_id),
                ],
                args=[session_id, repr(float(now - self.ttl_s)), encode_track(track, now), self._ttl_ms],
                client=client,
            )
        return bool(written == 1)

    async def get_tracks(self, vehicle_ids: Iterable[str]) -> Mapping[str, NeighbourTrack]:
        wanted = sorted(set(vehicle_ids))
        found: dict[str, NeighbourTrack] = {}
        now = self.clock()
        async with self._guard():
            client = await self._redis()
            for start in range(0, len(wanted), _CHUNK):
                chunk = wanted[start : start + _CHUNK]
                values = await self._mget(client, [self._track_key(vehicle) for vehicle in chunk])
                for vehicle, value in zip(chunk, values):
                    if value:
                        track, written_at = decode_track(vehicle, value)
                        if self.track_is_live(written_at, now):
                            found[vehicle] = track
        return found

    async def _mget(self, client: Any, keys: list[str]) -> list[bytes | None]:
        return list(await client.mget(keys))

    async def delete_track(self, vehicle_id: str) -> bool:
        async with self._guard():
            return bool(await (await self._redis()).delete(self._track_key(vehicle_id)))

    # request-rate limits --------------------------------------------------------------------
    async def take_request(self, key: str, limit: RateLimit) -> float:
        async with self._guard():
            client = await self._redis()
            wait = await self._evalsha(
                client,
                "take",
                [f"{self.rate_prefix}{key}"],
                [repr(float(self.clock())), repr(limit.interval_s), repr(limit.tolerance_s), repr(SLACK_S)],
            )
        return float(wait)

    async def request_wait(self, key: str, limit: RateLimit) -> float:
        async with self._guard():
            tat = await (await self._redis()).get(f"{self.rate_prefix}{key}")
        return gcra(None if tat is None else float(tat), self.clock(), limit)[0]

    # the fix stream -------------------------------------------------------------------------
    def fix_log(self, buffer: int) -> FixLog:
        from edgepos.store.redis_fixlog import RedisFixLog  # it builds on this module

        self._fix_buffer, self.fixes_in_write = buffer, self.APPENDS_FIXES_IN_WRITE
        return RedisFixLog(self, buffer)

    def _blocking_client(self, block_s: float) -> Any:
        """A client of its own (not the pool's) whose replies may take ``block_s`` more than the usual
        socket timeout: for XREAD BLOCK, which would otherwise hold a pooled connection the vehicles'
        batches need."""
        parts = urlsplit(self.url)
        query = dict(parse_qsl(parts.query, keep_blank_values=True))
        timeout = float(query.get("socket_timeout", DEFAULT_SOCKET_TIMEOUT_S)) + block_s
        query.update(socket_timeout=repr(timeout), max_connections="2")
        query.pop("timeout", None)  # the blocking pool's wait, not a connection option
        return Redis.from_url(urlunsplit(parts._replace(query=urlencode(query))))

    # lifecycle ------------------------------------------------------------------------------
    async def ping(self) -> bool:
        async with self._guard():
            return bool(await (await self._redis()).ping())

    async def close(self) -> None:
        """Close this loop's connections; a later call reconnects."""
        closer, self._closer, self._client = self._closer, None, None
        if closer is not None and self._loop is asyncio.get_running_loop():
            await closer.aclose()
