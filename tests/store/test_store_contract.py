"""Both stores keep the same contract: sessions with compare-and-set, TTL expiry, the session
limit, the RSU registry and the broadcast ephemerides."""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Iterator
from pathlib import Path

import pytest
from edgepos.pipelines.base import NeighbourTrack, Rsu, TrackPoint
from edgepos.store import MemoryStore, SessionRecord, SessionStore, SQLiteStore, TooManySessions, open_store
from edgepos.store.base import StoredEphemerides
from edgepos.store.ratelimit import RateLimit


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture(params=["memory", "sqlite"])
def store(request: pytest.FixtureRequest, tmp_path: Path, clock: Clock) -> Iterator[SessionStore]:
    instance: SessionStore
    if request.param == "memory":
        instance = MemoryStore(60.0, clock)
    else:
        instance = SQLiteStore(tmp_path / "store.db", 60.0, clock)
    yield instance
    asyncio.run(instance.close())


def record(session_id: str = "s1", now: float = 1000.0, **changes: object) -> SessionRecord:
    base = SessionRecord(
        session_id=session_id,
        vehicle_id="car",
        pipeline="rsu_imu",
        options={"filter": "ckf", "models": ["ca"]},
        token_hash="ab" * 32,
        state=b"\x00state\xff",
        created_at=now,
        updated_at=now,
    )
    return dataclasses.replace(base, **changes)


def test_create_get_round_trip(store):
    async def scenario() -> None:
        await store.create(record(), max_sessions=10)
        got = await store.get("s1")
        assert got == record()
        assert await store.get("other") is None

    asyncio.run(scenario())


def test_compare_and_set_bumps_the_version_once(store):
    async def scenario() -> None:
        await store.create(record(), max_sessions=10)
        current = await store.get("s1")
        updated = dataclasses.replace(
            current,
            state=b"new",
            last_seq=1,
            last_request_hash="h",
            last_response=b'{"seq":1}',
            batches=1,
            epochs=3,
            last_fix='{"t":1.0}',
            updated_at=1001.0,
        )
        assert await store.compare_and_set(updated, expected_version=0)
        assert await store.get("s1") == dataclasses.replace(updated, version=1)
        # a second writer holding the old version loses
        assert not await store.compare_and_set(
            dataclasses.replace(updated, state=b"lost"), expected_version=0
        )
        assert (await store.get("s1")).state == b"new"
        assert not await store.compare_and_set(record("missing"), expected_version=0)

    asyncio.run(scenario())


def test_returned_records_are_copies(store):
    async def scenario() -> None:
        await store.create(record(), max_sessions=10)
        got = await store.get("s1")
        got.options["filter"] = "ekf"
        assert (await store.get("s1")).options["filter"] == "ckf"

    asyncio.run(scenario())


def test_delete_and_count(store):
    async def scenario() -> None:
        for name in ("a", "b", "c"):
            await store.create(record(name), max_sessions=10)
        assert await store.count() == 3
        assert await store.delete("b")
        assert not await store.delete("b")
        assert await store.count() == 2

    asyncio.run(scenario())


def test_session_limit(store):
    async def scenario() -> None:
        await store.create(record("a"), max_sessions=2)
        await store.create(record("b"), max_sessions=2)
        with pytest.raises(TooManySessions):
            await store.create(record("c"), max_sessions=2)
        assert await store.get("c") is None
        await store.delete("a")
        await store.create(record("c"), max_sessions=2)

    asyncio.run(scenario())


def test_idle_sessions_expire(store, clock):
    async def scenario() -> None:
        await store.create(record("old"), max_sessions=2)
        clock.now += 30.0
        await store.create(record("young", now=clock.now), max_sessions=2)
        clock.now += 31.0  # "old" idle 61 s > ttl 60 s; "young" idle 31 s
        assert await store.get("old") is None
        assert await store.count() == 1
        assert (await store.get("young")) is not None
        await store.create(record("new", now=clock.now), max_sessions=2)  # the expired one no longer counts
        clock.now += 100.0
        assert await store.expire() == 2
        assert await store.count() == 0

    asyncio.run(scenario())


def test_a_write_keeps_a_session_alive(store, clock):
    async def scenario() -> None:
        await store.create(record(), max_sessions=2)
        clock.now += 50.0
        current = await store.get("s1")
        assert await store.compare_and_set(dataclasses.replace(current, updated_at=clock.now), 0)
        clock.now += 50.0
        assert await store.get("s1") is not None

    asyncio.run(scenario())


def test_rsu_registry(store):
    async def scenario() -> None:
        rsus = [Rsu("b", 1.0, 2.0), Rsu("a", -5.5, 0.25, range_std=0.5, bearing_std=0.01, radius=150.0)]
        assert await store.upsert_rsus(rsus) == 2
        assert await store.list_rsus() == sorted(rsus, key=lambda r: r.id)
        assert await store.get_rsu("a") == rsus[1]
        assert await store.get_rsus(["a", "zz", "a"]) == {"a": rsus[1]}
        assert await store.upsert_rsus([Rsu("a", 9.0, 9.0)]) == 1
        assert (await store.get_rsu("a")) == Rsu("a", 9.0, 9.0)
        assert await store.delete_rsu("a")
        assert not await store.delete_rsu("a")
        assert await store.get_rsu("a") is None

    asyncio.run(scenario())


def test_ephemerides_document(store):
    async def scenario() -> None:
        assert await store.get_ephemerides() is None
        assert await store.ephemerides_digest() is None
        assert not await store.delete_ephemerides()
        text = "     3.04           N: GNSS NAV DATA    M: Mixed            RINEX VERSION / TYPE\n\u00b5 \n" * 3
        first = StoredEphemerides("d1" * 32, text, 1000.5)
        await store.put_ephemerides(first)
        assert await store.get_ephemerides() == first
        assert await store.ephemerides_digest() == first.digest
        second = StoredEphemerides("e2" * 32, "other", 1001.0)
        await store.put_ephemerides(second)
        assert await store.get_ephemerides() == second
        assert await store.delete_ephemerides()
        assert await store.get_ephemerides() is None
        assert await store.ephemerides_digest() is None

    asyncio.run(scenario())


def test_many_rsu_lookups(store):
    async def scenario() -> None:
        await store.upsert_rsus(Rsu(f"r{i:04d}", float(i), 0.0) for i in range(1200))
        found = await store.get_rsus(f"r{i:04d}" for i in range(0, 1200, 1))
        assert len(found) == 1200 and found["r0999"].x == 999.0

    asyncio.run(scenario())


def test_rate_limit_allows_a_burst_then_the_rate(store, clock):
    """5 requests/s with bursts of 3: three at once pass, the fourth waits 0.2 s; budget comes back
    at the rate, a refused request uses none, and keys are independent."""
    limit = RateLimit(rate_per_s=5.0, burst=3)

    async def scenario() -> None:
        assert [await store.take_request("v1", limit) for _ in range(3)] == [0.0, 0.0, 0.0]
        assert await store.take_request("v1", limit) == pytest.approx(0.2)
        assert await store.take_request("v1", limit) == pytest.approx(0.2)  # refusals cost nothing
        assert await store.take_request("v2", limit) == 0.0
        clock.now += 0.1
        assert await store.take_request("v1", limit) == pytest.approx(0.1)
        clock.now += 0.1
        assert await store.take_request("v1", limit) == 0.0
        assert await store.take_request("v1", limit) == pytest.approx(0.2)
        clock.now += 10.0  # idle: the whole burst is back, not more
        assert [await store.take_request("v1", limit) for _ in range(3)] == [0.0, 0.0, 0.0]
        assert await store.take_request("v1", limit) > 0
        await store.expire()  # pruning keeps live budgets
        assert await store.take_request("v1", limit) > 0

    asyncio.run(scenario())


def test_rate_limit_config_is_checked():
    with pytest.raises(ValueError):
        RateLimit(rate_per_s=0.0, burst=1)
    with pytest.raises(ValueError):
        RateLimit(rate_per_s=1.0, burst=0)


def test_ping(store):
    assert asyncio.run(store.ping())


def test_open_store_by_url(tmp_path):
    assert isinstance(open_store("memory", 10.0), MemoryStore)
    sqlite_store = open_store(f"sqlite:///{tmp_path / 'x.db'}", 10.0)
    assert isinstance(sqlite_store, SQLiteStore) and sqlite_store.path == tmp_path / "x.db"
    with pytest.raises(ValueError):
        open_store("mongodb://localhost", 10.0)
    with pytest.raises(ValueError):
        MemoryStore(0.0)


# -- neighbour tracks ------------------------------------------------------------------------------
def track(vehicle_id: str = "car", count: int = 3, t0: float = 10.0) -> NeighbourTrack:
    cov = tuple(tuple(float(i == j) * (0.1 + i) + 1e-17 * (i + j) for j in range(4)) for i in range(4))
    points = tuple(TrackPoint(t0 + 0.2 * k, 1.0 / 3.0 + k, -2.5e5, 15.0, -0.1 * k, cov) for k in range(count))
    return NeighbourTrack(vehicle_id, points)


def test_track_round_trips_exactly_and_replaces_whole(store):
    async def scenario() -> None:
        assert await store.get_tracks(["car", "bus"]) == {}
        await store.put_track(track("car", 3))
        await store.put_track(track("bus", 1))
        got = await store.get_tracks(["car", "bus", "nobody"])
        assert got == {"car": track("car", 3), "bus": track("bus", 1)}
        await store.put_track(track("car", 2, t0=20.0))
        assert (await store.get_tracks(["car"]))["car"] == track("car", 2, t0=20.0)
        assert await store.delete_track("car")
        assert not await store.delete_track("car")
        assert await store.get_tracks(["car"]) == {}

    asyncio.run(scenario())


def test_track_expires_with_the_session_ttl(store, clock):
    async def scenario() -> None:
        await store.put_track(track("car"))
        clock.now += 59.0
        assert "car" in await store.get_tracks(["car"])
        clock.now += 2.0
        assert await store.get_tracks(["car"]) == {}

    asyncio.run(scenario())


def test_concurrent_track_writers_never_expose_a_mix(store):
    """Two vehicles publishing while a third reads: every read is one whole published track."""
    versions = {vehicle: [track(vehicle, count, t0=float(count)) for count in range(1, 12)] for vehicle in ("a", "b")}

    async def writer(vehicle: str) -> None:
        for version in versions[vehicle]:
            await store.put_track(version)
            await asyncio.sleep(0)

    async def reader(seen: list[NeighbourTrack]) -> None:
        for _ in range(40):
            seen.extend((await store.get_tracks(["a", "b"])).values())
            await asyncio.sleep(0)

    async def scenario() -> list[NeighbourTrack]:
        seen: list[NeighbourTrack] = []
        await asyncio.wait_for(asyncio.gather(writer("a"), writer("b"), reader(seen)), timeout=30)
        return seen

    for got in asyncio.run(scenario()):
        assert got in versions[got.vehicle_id]
