"""Reference stations in Redis, shared by the Redis stores (``store.redis``, ``store.redis_cluster``): the
stations in one hash, each station's correction window in a sorted set scored by GPS seconds. All under the
hash tag ``{basestations}``, so on a Redis Cluster they share one slot and a batch's read (the station and
its window) is one round trip of one transaction (see docs/redis.md)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from contextlib import AbstractAsyncContextManager
from typing import TYPE_CHECKING, Any

from edgepos.store.base import BaseWindow, StoredBaseStation

if TYPE_CHECKING:
    from redis.commands.core import AsyncScript


def _station(station_id: str, value: bytes | str) -> StoredBaseStation:
    document, updated_at = json.loads(value)
    return StoredBaseStation(station_id, str(document), float(updated_at))


def _value(station: StoredBaseStation) -> str:
    return json.dumps([station.document, float(station.updated_at)])


def _epoch(member: bytes) -> tuple[float, str]:
    """A window member is ``repr(gpst)|document``: the time makes members of equal documents distinct."""
    gpst, document = bytes(member).decode().split("|", 1)
    return float(gpst), document


class RedisBaseStations:
    """The reference-station part of a Redis store (a base of ``RedisStore``)."""

    prefix: str
    _scripts: dict[str, AsyncScript]

    if TYPE_CHECKING:

        def _guard(self) -> AbstractAsyncContextManager[None]: ...

        async def _redis(self) -> Any: ...

    @property
    def base_stations_key(self) -> str:
        return f"{self.prefix}{{basestations}}:stations"

    def base_epochs_key(self, station_id: str) -> str:
        return f"{self.prefix}{{basestations}}:epochs:{station_id}"

    async def add_base_station(self, station: StoredBaseStation) -> bool:
        async with self._guard():
            client = await self._redis()
            return bool(await client.hsetnx(self.base_stations_key, station.station_id, _value(station)))

    async def replace_base_station(self, station: StoredBaseStation) -> bool:
        async with self._guard():
            client = await self._redis()
            replaced = await self._scripts["replace_base_station"](
                keys=[self.base_stations_key], args=[station.station_id, _value(station)], client=client
            )
        return bool(replaced)

    async def get_base_station(self, station_id: str) -> StoredBaseStation | None:
        async with self._guard():
            value = await (await self._redis()).hget(self.base_stations_key, station_id)
        return None if value is None else _station(station_id, value)

    async def list_base_stations(self) -> list[StoredBaseStation]:
        async with self._guard():
            raw = await (await self._redis()).hgetall(self.base_stations_key)
        stations = [_station(bytes(key).decode(), value) for key, value in raw.items()]
        return sorted(stations, key=lambda station: station.station_id)

    async def delete_base_station(self, station_id: str) -> bool:
        async with self._guard(), (await self._redis()).pipeline(transaction=True) as pipe:
            pipe.hdel(self.base_stations_key, station_id)
            pipe.delete(self.base_epochs_key(station_id))
            removed, _ = await pipe.execute()
        return bool(removed)

    async def add_base_epochs(
        self, station_id: str, epochs: Sequence[tuple[float, str]], keep: int
    ) -> int | None:
        args: list[Any] = [station_id, int(keep)]
        for gpst, document in epochs:
            args += [repr(float(gpst)), f"{float(gpst)!r}|{document}"]
        async with self._guard():
            client = await self._redis()
            size = await self._scripts["add_base_epochs"](
                keys=[self.base_stations_key, self.base_epochs_key(station_id)], args=args, client=client
            )
        return None if int(size) < 0 else int(size)

    async def base_window(self, station_id: str, since: float, until: float) -> BaseWindow | None:
        key = self.base_epochs_key(station_id)
        async with self._guard(), (await self._redis()).pipeline(transaction=True) as pipe:
            pipe.hget(self.base_stations_key, station_id)
            pipe.zrevrangebyscore(key, f"({float(since)!r}", "-inf", start=0, num=1)
            pipe.zrangebyscore(key, repr(float(since)), repr(float(until)))
            value, before, inside = await pipe.execute()
        if value is None:
            return None
        return BaseWindow(_station(station_id, value), tuple(_epoch(m) for m in [*before, *inside]))
