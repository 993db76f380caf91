"""The Redis store on a Redis Cluster (``redis-cluster://host:port[,host:port...]``).

Redis Cluster runs a script or a transaction only when all its keys hash to one slot. The store
therefore cuts the sessions into :data:`SHARDS` shards and names every key of a shard with the same
hash tag: a vehicle belongs to the shard given by a hash of its id, and a session id carries its
vehicle's shard in its first two hex digits (:meth:`RedisClusterStore.new_session_id`), so the
session hash, the vehicle's live pointer and track, the supersession record and the shard's index of
live sessions share one slot, and every script of the single-node store (create with supersession,
compare-and-set, delete, publish a track) runs unchanged and atomically on one primary. The shards'
hash tags are chosen so that their slots lie evenly over the 16384 slots: a cluster whose primaries
hold equal slot ranges holds equal shares of the sessions.

What spans shards is done shard by shard, never in a cross-slot transaction:

* the session limit: the count of the other shards (one pipelined ZCOUNT per shard, one round trip per
  node) is passed to the create script, which checks its own shard exactly; concurrent creates on
  other shards can overshoot the limit by at most their number;
* the vehicle registry lives in one slot of its own; creating a session checks the vehicle key
  before and again after the create script and deletes what it created if the vehicle was revoked in
  between, and revocation deregisters first and then ends the live session, so a revoked vehicle
  never keeps a session;
* the RSU registry, the ephemerides and each request-rate budget are single keys;
* neighbour tracks are read with MGET grouped by slot, one round trip per node.

With ``wait_replicas`` a batch is acknowledged once its primary's replicas have it: after the
compare-and-set a write to the shard's ``durable`` key and WAIT on one connection to that primary
(the replication stream is ordered, so the replicas then hold the batch too).
"""

from __future__ import annotations

import asyncio
import hashlib
import secrets
import time
from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from functools import cache
from typing import Any
from urllib.parse import parse_qsl, unquote, urlsplit

from redis import exceptions as redis_errors
from redis.asyncio import Redis
from redis.asyncio.cluster import ClusterNode, RedisCluster
from redis.asyncio.retry import Retry
from redis.backoff import ExponentialBackoff
from redis.crc import REDIS_CLUSTER_HASH_SLOTS, key_slot

from edgepos.store import redis_scripts as scripts
from edgepos.store.base import Clock, Revocation, SessionRecord, TooManySessions, VehicleNotRegistered
from edgepos.store.redis import RedisStore
from edgepos.store.redis_round_trip import Command, allow_for_wait
from edgepos.store.redis_url import (
    DEFAULT_CONNECT_TIMEOUT_S,
    DEFAULT_MAX_CONNECTIONS,
    DEFAULT_PREFIX,
    DEFAULT_SOCKET_TIMEOUT_S,
)

SCHEME = "redis-cluster"
SHARDS = 256
"""Shards of the session keys. Each is one hash slot, so at most this many primaries share the
sessions; 256 evenly spread slots give each of three primaries its third within 1 %."""
COUNT_CACHE_S = 1.0
"""How long one worker reuses the other shards' session count while the total is below
:data:`COUNT_CACHE_BELOW` of the limit (near the limit every create counts afresh)."""
COUNT_CACHE_BELOW = 0.9
_REDIRECT_ATTEMPTS = 3
_SPARE_CONNECTIONS = 32
"""Connections per node beyond the operations a worker runs at once, for the shard sweeps that one
operation fans out (the cluster client refuses, rather than waits, past its connection limit)."""
_OPTIONS = {"prefix", "record_cache", "socket_timeout", "socket_connect_timeout", "max_connections", "ssl"}


def parse_cluster_url(url: str) -> dict[str, Any]:
    """``redis-cluster://[user:password@]host:port[,host:port...][?prefix=..&socket_timeout=..]`` as
    the store's settings: ``nodes`` (startup nodes), ``prefix`` and the client's keyword arguments."""
    # The host list is split off by hand: urlsplit checks a netloc as one host, and some builds (Debian's
    # 3.11.2, seen) refuse a list whose later entry is a bracketed IPv6 address ("Invalid IPv6 URL").
    scheme, separator, rest = url.partition("://")
    if scheme.lower() != SCHEME or not separator:
        raise ValueError(f"not a Redis Cluster URL (want {SCHEME}://host:port[,host:port...]): {url!r}")
    ends = [index for index in (rest.find(mark) for mark in "/?#") if index >= 0]
    netloc, tail = rest[: min(ends, default=len(rest))], rest[min(ends, default=len(rest)) :]
    parts = urlsplit(f"{SCHEME}://host{tail}")  # the path, query and fragment after the host list
    userinfo, _, hosts = netloc.rpartition("@")
    nodes: list[tuple[str, int]] = []
    for item in hosts.split(","):
        host, _, port = item.strip().rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"a Redis Cluster node must be host:port, got {item!r} in {url!r}")
        nodes.append((host.strip("[]"), int(port)))
    query = dict(parse_qsl(parts.query, keep_blank_values=True))
    unknown = sorted(set(query) - _OPTIONS)
    if unknown:
        raise ValueError(f"unknown Redis Cluster URL option(s) {unknown}; known: {sorted(_OPTIONS)}")
    prefix = query.get("prefix", DEFAULT_PREFIX)
    if not prefix or "{" in prefix or "}" in prefix:
        raise ValueError(
            "the Redis key prefix must be non-empty and free of '{' and '}' (they mark hash tags)"
        )
    client: dict[str, Any] = {
        "socket_timeout": float(query.get("socket_timeout", DEFAULT_SOCKET_TIMEOUT_S)),
        "socket_connect_timeout": float(query.get("socket_connect_timeout", DEFAULT_CONNECT_TIMEOUT_S)),
        "max_connections": int(query.get("max_connections", DEFAULT_MAX_CONNECTIONS)),
        "ssl": query.get("ssl", "false").lower() in ("1", "true", "yes"),
    }
    if userinfo:
        username, colon, password = userinfo.partition(":")
        client["username"] = unquote(username) or None
        client["password"] = unquote(password) if colon else None
    return {"nodes": nodes, "prefix": prefix, "client": client}


@cache
def shard_tags() -> tuple[str, ...]:
    """For shard ``i`` the smallest decimal number (as text) whose hash slot lies in the ``i``-th of
    :data:`SHARDS` equal slot ranges: the shards lie evenly over the slots, whatever their number."""
    width = REDIS_CLUSTER_HASH_SLOTS // SHARDS
    tags: list[str | None] = [None] * SHARDS
    missing, number = SHARDS, 0
    while missing:
        text = str(number)
        shard = key_slot(text.encode()) // width
        if tags[shard] is None:
            tags[shard] = text
            missing -= 1
        number += 1
    return tuple(tag for tag in tags if tag is not None)


def shard_of_vehicle(vehicle_id: str) -> int:
    return int.from_bytes(hashlib.sha256(vehicle_id.encode()).digest()[:4], "big") % SHARDS


def shard_of_session(session_id: str) -> int:
    """The shard named by a session id's first two hex digits (ids from ``new_session_id``)."""
    head = session_id[:2]
    if len(head) == 2 and all(c in "0123456789abcdef" for c in head):
        return int(head, 16) % SHARDS
    return shard_of_vehicle(session_id)  # not an id of ours: a shard where it is simply not found


class RedisClusterStore(RedisStore):
    """The Redis store's contract on a Redis Cluster, with the key layout described above."""

    SCRIPTS: Mapping[str, str] = {
        **RedisStore.SCRIPTS,
        "deregister": scripts.DEREGISTER_VEHICLE,
        "end_vehicle_session": scripts.END_VEHICLE_SESSION,
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
        self.settings = parse_cluster_url(url)
        super().__init__(url, ttl_s, clock, wait_replicas=wait_replicas, wait_timeout_ms=wait_timeout_ms)
        allow_for_wait(self.settings["client"], wait_timeout_ms if wait_replicas else 0)
        tags = shard_tags()
        self._shard_prefixes = tuple(f"{self.prefix}{{{tag}}}:" for tag in tags)
        self.vehicles_key = f"{self.prefix}{{registry}}:vehicles"
        self.vehicle_keys_key = f"{self.prefix}{{registry}}:vehiclekeys"
        self._node_clients: dict[str, Redis] = {}
        self._counts: tuple[float, list[int]] | None = None  # (monotonic time, sessions per shard)
        self._permits = asyncio.Semaphore(1)  # replaced with the client, per event loop
        # the RSU map's token lives in another slot than a session's keys, which the compare-and-set
        # script alone may touch here: every batch reads the RSUs it needs (store.redis_cache)
        self.cache_rsus = False

    @staticmethod
    def _parse_url(url: str) -> tuple[str, str]:
        return url, parse_cluster_url(url)["prefix"]

    def _connect(self) -> Any:
        settings = self.settings
        # The cluster client raises instead of waiting when a node's connections are all busy: operations
        # wait for one of max_connections permits instead (each holds at most one connection per node).
        self._permits = asyncio.Semaphore(settings["client"]["max_connections"])
        return RedisCluster(
            startup_nodes=[ClusterNode(host, port) for host, port in settings["nodes"]],
            require_full_coverage=False,  # the shards on healthy primaries keep working during a failover
            # A few topology refreshes and redirections, backing off to about a node timeout in all
            # (failover of a primary), then StoreUnavailable: bounded, never a hang.
            retry=Retry(ExponentialBackoff(cap=0.5, base=0.1), retries=4),
            **{
                **settings["client"],
                "max_connections": settings["client"]["max_connections"] + _SPARE_CONNECTIONS,
            },
        )

    def _blocking_client(self, block_s: float) -> Any:
        """A cluster client of its own for XREAD BLOCK on the fix stream (one slot: one node's connection)."""
        settings = self.settings["client"]
        return RedisCluster(
            startup_nodes=[ClusterNode(host, port) for host, port in self.settings["nodes"]],
            require_full_coverage=False,
            retry=Retry(ExponentialBackoff(cap=0.5, base=0.1), retries=4),
            **{**settings, "socket_timeout": settings["socket_timeout"] + block_s, "max_connections": 2},
        )

    @asynccontextmanager
    async def _guard(self) -> AsyncIterator[None]:
        await self._redis()  # this loop's client and permits
        async with self._permits, super()._guard():
            yield

    # key names ------------------------------------------------------------------------------
    def new_session_id(self, vehicle_id: str) -> str:
        return f"{shard_of_vehicle(vehicle_id):02x}{secrets.token_hex(15)}"

    def _session_prefix_of(self, session_id: str) -> str:
        return f"{self._shard_prefixes[shard_of_session(session_id)]}session:"

    def _index_key(self, session_id: str) -> str:
        return self._shard_index(shard_of_session(session_id))

    def _shard_index(self, shard: int) -> str:
        return f"{self._shard_prefixes[shard]}sessions"

    def _superseded_key(self, session_id: str) -> str:
        return f"{self._shard_prefixes[shard_of_session(session_id)]}superseded:{session_id}"

    def _registry_key_for_create(self, session_id: str) -> str:
        # never read: the cluster create checks the registry in its own slot (see create)
        return f"{self._shard_prefixes[shard_of_session(session_id)]}registry-unused"

    def _vehicle_prefix(self, vehicle_id: str, session_id: str | None) -> str:
        shard = shard_of_vehicle(vehicle_id) if session_id is None else shard_of_session(session_id)
        return self._shard_prefixes[shard]

    def _live_key(self, vehicle_id: str, session_id: str | None = None) -> str:
        return f"{self._vehicle_prefix(vehicle_id, session_id)}live:{vehicle_id}"

    def _track_key(self, vehicle_id: str, session_id: str | None = None) -> str:
        return f"{self._vehicle_prefix(vehicle_id, session_id)}track:{vehicle_id}"

    # sessions -------------------------------------------------------------------------------
    async def _shard_counts(self, *, fresh: bool) -> list[int]:
        """Live sessions per shard: one pipelined ZCOUNT per shard (a round trip per node)."""
        cached = self._counts
        if not fresh and cached is not None and time.monotonic() - cached[0] < COUNT_CACHE_S:
            return cached[1]
        cutoff = self._cutoff()
        async with self._guard():
            pipe = (await self._redis()).pipeline(transaction=False)
            for shard in range(SHARDS):
                pipe.zcount(self._shard_index(shard), cutoff, "+inf")
            counts = [int(count) for count in await pipe.execute()]
        self._counts = (time.monotonic(), counts)
        return counts

    async def _registered_with(self, vehicle_id: str, key_hash: str) -> bool:
        vehicle = await self.get_vehicle(vehicle_id)
        return vehicle is not None and vehicle.key_hash == key_hash

    async def create(
        self, record: SessionRecord, max_sessions: int, *, vehicle_key_hash: str | None = None
    ) -> str | None:
        shard = shard_of_session(record.session_id)
        if shard != shard_of_vehicle(record.vehicle_id):
            raise ValueError(
                f"session id {record.session_id!r} is not in vehicle {record.vehicle_id!r}'s shard; "
                "take session ids from new_session_id"
            )
        if vehicle_key_hash is not None and not await self._registered_with(
            record.vehicle_id, vehicle_key_hash
        ):
            raise VehicleNotRegistered(record.vehicle_id)
        counts = await self._shard_counts(fresh=False)
        if sum(counts) + 1 >= COUNT_CACHE_BELOW * max_sessions:
            counts = await self._shard_counts(fresh=True)
        others = sum(counts) - counts[shard]
        try:
            # the script checks its own shard against what the others leave of the limit
            superseded = await super().create(record, max_sessions - others)
        except TooManySessions:
            raise TooManySessions(max_sessions) from None
        counts[shard] += 1
        if vehicle_key_hash is not None and not await self._registered_with(
            record.vehicle_id, vehicle_key_hash
        ):
            await self.delete(record.session_id)  # revoked or re-keyed meanwhile: keep nothing
            raise VehicleNotRegistered(record.vehicle_id)
        return superseded

    async def _indexed_session_ids(self, client: Any) -> list[str]:
        cutoff = self._cutoff()
        pipe = client.pipeline(transaction=False)
        for shard in range(SHARDS):
            pipe.zrangebyscore(self._shard_index(shard), cutoff, "+inf")
        return [bytes(member).decode() for members in await pipe.execute() for member in members]

    async def _purge_and_count(self) -> tuple[int, int]:
        """Every shard's purge-and-count script, concurrently (scripts cannot be pipelined on a cluster)."""
        cutoff = self._cutoff()
        async with self._guard():
            client = await self._redis()
            replies = []
            for start in range(0, SHARDS, _SPARE_CONNECTIONS):
                replies += await asyncio.gather(
                    *(
                        self._scripts["count"](
                            keys=[self._shard_index(shard)],
                            args=[cutoff, f"{self._shard_prefixes[shard]}session:"],
                            client=client,
                        )
                        for shard in range(start, start + _SPARE_CONNECTIONS)
                    )
                )
        counts = [int(left) for _, left in replies]
        self._counts = (time.monotonic(), counts)
        return sum(int(gone) for gone, _ in replies), sum(counts)

    APPENDS_FIXES_IN_WRITE = False  # the stream's slot is not the session's: its appends go apart

    async def _staged_write(
        self, client: Any, keys: list[str], args: list[bytes | str | int], fields: list[bytes], script: str
    ) -> tuple[int, int]:
        """As the single server's, the three commands to the session's slot in one pipeline; WAIT then goes
        to the primary that holds the slot (a cluster pipeline cannot route WAIT)."""
        replies = await self._staged_pipeline(client, keys, args, fields, script, wait=False)
        applied = int(replies[2])
        session_id = str(args[3])
        replicas = await self._wait_on_shard(session_id) if applied == 1 and self.wait_replicas else 0
        return applied, replicas

    async def _round_trip(self, client: Any, commands: list[Command]) -> list[Any]:
        """A cluster pipeline: it sends each command to the primary of its slot (one here: the session's)."""
        pipe = client.pipeline(transaction=False)
        for command in commands:
            pipe.execute_command(*command)
        return list(await pipe.execute(raise_on_error=False))

    async def _evalsha(self, client: Any, name: str, keys: list[str], args: list[Any]) -> Any:
        """redis-py's script object, which the cluster client routes to the keys' slot."""
        return await self._scripts[name](keys=keys, args=args, client=client)

    async def make_durable(self, session_id: str) -> None:
        if not self.wait_replicas:
            return
        async with self._guard():
            replicas = await self._wait_on_shard(session_id)
        self._check_replicas(replicas, "the stored answer")

    async def _wait_on_shard(self, session_id: str) -> int:
        """A write to the session's shard and WAIT, on one connection to the primary that holds the
        shard's slot now (after a redirection: the primary it moved to); the replicas that have it."""
        key = f"{self._shard_prefixes[shard_of_session(session_id)]}durable"
        cluster = await self._redis()
        attempt = 0
        while True:
            attempt += 1
            node = cluster.get_node_from_key(key)
            pipe = self._node_client(node.host, node.port).pipeline(transaction=False)
            pipe.set(key, b"1")
            pipe.execute_command("WAIT", self.wait_replicas, self.wait_timeout_ms)
            try:
                _, replicas = await pipe.execute()
            except (redis_errors.AskError, redis_errors.TryAgainError):  # MovedError is an AskError
                if attempt >= _REDIRECT_ATTEMPTS:
                    raise
                await cluster.nodes_manager.initialize()  # the slot moved: learn where to
                continue
            return int(replicas)

    def _node_client(self, host: str, port: int) -> Redis:
        """A plain client of one primary, for WAIT (it counts the writes of its own connection)."""
        name = f"{host}:{port}"
        client = self._node_clients.get(name)
        if client is None:
            settings = self.settings["client"]
            client = Redis(
                host=host,
                port=port,
                socket_timeout=settings["socket_timeout"],
                socket_connect_timeout=settings["socket_connect_timeout"],
                username=settings.get("username"),
                password=settings.get("password"),
                ssl=settings["ssl"],
                single_connection_client=False,
            )
            self._node_clients[name] = client
        return client

    # vehicle registry -----------------------------------------------------------------------
    async def delete_vehicle(self, vehicle_id: str) -> Revocation | None:
        async with self._guard():
            client = await self._redis()
            registered = await self._scripts["deregister"](
                keys=[self.vehicles_key, self.vehicle_keys_key], args=[vehicle_id], client=client
            )
            if int(registered) == 0:
                return None
            shard = shard_of_vehicle(vehicle_id)
            ended = await self._scripts["end_vehicle_session"](
                keys=[self._live_key(vehicle_id), self._track_key(vehicle_id), self._shard_index(shard)],
                args=[f"{self._shard_prefixes[shard]}session:", self._cutoff()],
                client=client,
            )
        ended_id = bytes(ended).decode()
        self.records.drop(ended_id)
        return Revocation(vehicle_id, ended_id or None)

    # neighbour tracks -----------------------------------------------------------------------
    async def _mget(self, client: Any, keys: list[str]) -> list[bytes | None]:
        return list(await client.mget_nonatomic(keys))  # grouped by slot: one round trip per node

    # lifecycle ------------------------------------------------------------------------------
    def _discard_client(self) -> None:
        super()._discard_client()
        for client in self._node_clients.values():  # they may hold reset connections too
            task = asyncio.get_running_loop().create_task(client.aclose())
            self._closing.add(task)
            task.add_done_callback(self._closing.discard)
        self._node_clients = {}

    async def close(self) -> None:
        clients, self._node_clients = list(self._node_clients.values()), {}
        for client in clients:
            await client.aclose()
        await super().close()
