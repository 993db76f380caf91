"""The site's registries in Redis, shared by the Redis stores (``store.redis``, ``store.redis_cluster``):
registered vehicles (a hash by vehicle id and one by key hash, written together by Lua scripts), the
RSU map (one hash), the broadcast ephemerides (one hash replaced in one transaction), the location
adapter's documents (one hash per kind) and leases (one key each). Each is one key or, for the
vehicles, two keys of one hash slot (see docs/redis.md)."""

from __future__ import annotations

import json
import math
import secrets
from collections.abc import Iterable, Mapping, Sequence
from contextlib import AbstractAsyncContextManager
from typing import TYPE_CHECKING, Any

from edgepos.pipelines.base import Rsu
from edgepos.store.base import StoredEphemerides, VehicleRecord
from edgepos.store.redis_cache import RSUS_USED, RsuSnapshot

_CHUNK = 500

if TYPE_CHECKING:
    from redis.commands.core import AsyncScript


def _vehicle_value(vehicle: VehicleRecord) -> str:
    return json.dumps([vehicle.key_hash, float(vehicle.created_at), float(vehicle.key_issued_at)])


def _vehicle(vehicle_id: str, value: bytes | str) -> VehicleRecord:
    key_hash, created_at, key_issued_at = json.loads(value)
    return VehicleRecord(vehicle_id, key_hash, float(created_at), float(key_issued_at))


def _rsu_value(rsu: Rsu) -> str:
    return json.dumps([rsu.x, rsu.y, rsu.range_std, rsu.bearing_std, rsu.radius])


def _rsu(rsu_id: str, value: bytes) -> Rsu:
    x, y, range_std, bearing_std, radius = json.loads(value)
    return Rsu(rsu_id, x, y, range_std, bearing_std, radius)


class RedisRegistry:
    """Vehicles, RSUs and ephemerides of a Redis store (a base of ``RedisStore``, which provides the
    client, the scripts, the error translation and the key names)."""

    vehicles_key: str
    vehicle_keys_key: str
    rsu_key: str
    rsu_token_key: str
    cache_rsus: bool
    _rsus: RsuSnapshot | None
    ephemerides_key: str
    documents_prefix: str
    lease_prefix: str
    _scripts: dict[str, AsyncScript]

    if TYPE_CHECKING:

        def _guard(self) -> AbstractAsyncContextManager[None]: ...

        async def _redis(self) -> Any: ...

    # vehicle registry -----------------------------------------------------------------------
    async def add_vehicles(self, vehicles: Sequence[VehicleRecord]) -> list[str]:
        args = [item for v in vehicles for item in (v.vehicle_id, v.key_hash, _vehicle_value(v))]
        if not args:
            return []
        async with self._guard():
            client = await self._redis()
            added = await self._scripts["add_vehicles"](
                keys=[self.vehicles_key, self.vehicle_keys_key], args=args, client=client
            )
        if added and not isinstance(added[0], bytes):
            raise ValueError("a vehicle key hash is already another vehicle's; nothing was added")
        return [bytes(vehicle_id).decode() for vehicle_id in added]

    async def get_vehicle(self, vehicle_id: str) -> VehicleRecord | None:
        async with self._guard():
            value = await (await self._redis()).hget(self.vehicles_key, vehicle_id)
        return None if value is None else _vehicle(vehicle_id, value)

    async def vehicle_of_key(self, key_hash: str) -> str | None:
        async with self._guard():
            vehicle_id = await (await self._redis()).hget(self.vehicle_keys_key, key_hash)
        return None if vehicle_id is None else bytes(vehicle_id).decode()

    async def list_vehicles(self, *, after: str | None = None, limit: int = 100) -> list[VehicleRecord]:
        async with self._guard():
            raw = await (await self._redis()).hgetall(self.vehicles_key)
        ids = sorted(key.decode() for key in raw)
        if after is not None:
            ids = [vehicle_id for vehicle_id in ids if vehicle_id > after]
        return [_vehicle(vehicle_id, raw[vehicle_id.encode()]) for vehicle_id in ids[: max(0, limit)]]

    async def count_vehicles(self) -> int:
        async with self._guard():
            return int(await (await self._redis()).hlen(self.vehicles_key))

    async def rotate_vehicle_key(self, vehicle_id: str, key_hash: str, now: float) -> VehicleRecord | None:
        async with self._guard():
            client = await self._redis()
            rotated = await self._scripts["rotate"](
                keys=[self.vehicles_key, self.vehicle_keys_key],
                args=[vehicle_id, key_hash, repr(float(now))],
                client=client,
            )
        if rotated == 0:
            return None
        if rotated == -1:
            raise ValueError("the new key hash is already another vehicle's; the key was not rotated")
        return _vehicle(vehicle_id, rotated)

    # RSUs -----------------------------------------------------------------------------------
    async def upsert_rsus(self, rsus: Iterable[Rsu]) -> int:
        mapping = {rsu.id: _rsu_value(rsu) for rsu in rsus}
        if not mapping:
            return 0
        items = list(mapping.items())
        async with self._guard(), (await self._redis()).pipeline(transaction=True) as pipe:
            for start in range(0, len(items), _CHUNK):
                pipe.hset(self.rsu_key, mapping=dict(items[start : start + _CHUNK]))
            await pipe.execute()
        await self._new_rsu_token()
        return len(mapping)

    async def _new_rsu_token(self) -> None:
        """After every RSU write (not before: a map read with the new token is then the new map): a fresh
        random token, so that a batch computed on a map cached before the write is refused by its
        compare-and-set. Random, not a counter: a map cached before Redis lost its data never matches.
        None on a store that does not cache the map (a Redis Cluster)."""
        self._rsus = None
        if not self.cache_rsus:
            return
        async with self._guard():
            await (await self._redis()).set(self.rsu_token_key, secrets.token_hex(8))

    async def get_rsu(self, rsu_id: str) -> Rsu | None:
        return (await self.get_rsus([rsu_id])).get(rsu_id)

    async def get_rsus(self, rsu_ids: Iterable[str]) -> Mapping[str, Rsu]:
        """The RSUs of ``rsu_ids`` that are registered. With ``cache_rsus``, from this worker's copy of the
        whole map, read once per RSU write (its token marks the batch's compare-and-set: see redis_cache)."""
        if self.cache_rsus:
            snapshot = self._rsus if self._rsus is not None else await self._read_rsu_map()
            RSUS_USED.set(snapshot.token)
            return {rsu_id: snapshot.rsus[rsu_id] for rsu_id in set(rsu_ids) if rsu_id in snapshot.rsus}
        wanted = sorted(set(rsu_ids))
        found: dict[str, Rsu] = {}
        async with self._guard():
            client = await self._redis()
            for start in range(0, len(wanted), _CHUNK):
                chunk = wanted[start : start + _CHUNK]
                values = await client.hmget(self.rsu_key, chunk)
                found.update({rid: _rsu(rid, value) for rid, value in zip(chunk, values) if value})
        return found

    async def _read_rsu_map(self) -> RsuSnapshot:
        """The whole map and its token in one transaction (one round trip), kept as this worker's copy."""
        async with self._guard(), (await self._redis()).pipeline(transaction=True) as pipe:
            pipe.get(self.rsu_token_key)
            pipe.hgetall(self.rsu_key)
            token, raw = await pipe.execute()
        snapshot = RsuSnapshot(
            "" if token is None else bytes(token).decode(),
            {key.decode(): _rsu(key.decode(), value) for key, value in raw.items()},
        )
        self._rsus = snapshot
        return snapshot

    def forget_rsus(self) -> None:
        """Drop this worker's copy of the RSU map (a write refused its token: the map changed)."""
        self._rsus = None

    async def list_rsus(self) -> list[Rsu]:
        async with self._guard():
            raw = await (await self._redis()).hgetall(self.rsu_key)
        rsus = [_rsu(key.decode(), value) for key, value in raw.items()]
        return sorted(rsus, key=lambda rsu: rsu.id)

    async def delete_rsu(self, rsu_id: str) -> bool:
        async with self._guard():
            removed = bool(await (await self._redis()).hdel(self.rsu_key, rsu_id))
        await self._new_rsu_token()
        return removed

    # broadcast ephemerides ------------------------------------------------------------------
    async def put_ephemerides(self, document: StoredEphemerides) -> None:
        async with self._guard(), (await self._redis()).pipeline(transaction=True) as pipe:
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

    # documents of the location adapter and leases ---------------------------------------------
    async def put_document(self, kind: str, key: str, text: str) -> None:
        async with self._guard():
            await (await self._redis()).hset(self.documents_prefix + kind, key, text.encode())

    async def replace_document(self, kind: str, key: str, text: str) -> bool:
        async with self._guard():
            client = await self._redis()
            written = await self._scripts["replace_document"](
                keys=[self.documents_prefix + kind], args=[key, text.encode()], client=client
            )
        return bool(written == 1)

    async def get_document(self, kind: str, key: str) -> str | None:
        async with self._guard():
            text = await (await self._redis()).hget(self.documents_prefix + kind, key)
        return None if text is None else bytes(text).decode()

    async def list_documents(self, kind: str) -> dict[str, str]:
        async with self._guard():
            raw = await (await self._redis()).hgetall(self.documents_prefix + kind)
        documents = {bytes(key).decode(): bytes(text).decode() for key, text in raw.items()}
        return {key: documents[key] for key in sorted(documents)}

    async def delete_document(self, kind: str, key: str) -> bool:
        async with self._guard():
            return bool(await (await self._redis()).hdel(self.documents_prefix + kind, key))

    async def acquire_lease(self, name: str, owner: str, ttl_s: float) -> bool:
        ttl_ms = max(1, math.ceil(ttl_s * 1000.0))
        async with self._guard():
            client = await self._redis()
            held = await self._scripts["acquire_lease"](
                keys=[self.lease_prefix + name], args=[owner, ttl_ms], client=client
            )
        return bool(held == 1)
