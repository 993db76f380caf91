"""Every store keeps the same contract: sessions with compare-and-set, TTL expiry, the session
limit, one live session per vehicle (a new one supersedes the old), the vehicle registry, the RSU
registry, the broadcast ephemerides, neighbour tracks and request-rate limits. (test_store_redis.py
runs these tests again on the Redis store.)"""

from __future__ import annotations

import asyncio
import dataclasses
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest
from edgepos.pipelines.base import NeighbourTrack, Rsu, TrackPoint
from edgepos.store import MemoryStore, SessionRecord, SessionStore, SQLiteStore, TooManySessions, open_store
from edgepos.store.base import (
    BaseWindow,
    Revocation,
    SessionSummary,
    StoredBaseStation,
    StoredEphemerides,
    Supersession,
    VehicleNotRegistered,
    VehicleRecord,
)
from edgepos.store.fixlog import NewFix
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


@pytest.fixture
def handles(store: SessionStore, clock: Clock) -> Iterator[list[SessionStore]]:
    """Several handles on the same data, as several workers would hold them (more connections to
    the SQLite file, each with its own thread; the in-process store has only itself)."""
    if isinstance(store, SQLiteStore):
        others = [SQLiteStore(store.path, 60.0, clock) for _ in range(3)]
        yield [store, *others]
        for other in others:
            asyncio.run(other.close())
    else:
        yield [store]


def record(session_id: str = "s1", now: float = 1000.0, **changes: object) -> SessionRecord:
    """A session of its own vehicle (``v-<session id>``) unless ``vehicle_id`` is given."""
    base = SessionRecord(
        session_id=session_id,
        vehicle_id=f"v-{session_id}",
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


def test_a_record_read_or_written_shares_nothing_with_the_store(store):
    """Changing the options of a record after writing it, or of one read back, changes nothing stored
    (nested values included): the in-process store copies them instead of keeping the caller's dict."""

    async def scenario() -> None:
        options = {"filter": "ckf", "models": ["ca"], "model_params": {"singer": {"sigma": 1.0}}}
        written = record(options=options)
        await store.create(written, max_sessions=10)
        options["models"].append("ct")
        options["model_params"]["singer"]["sigma"] = 9.0
        read = await store.get("s1")
        assert read.options == {"filter": "ckf", "models": ["ca"], "model_params": {"singer": {"sigma": 1.0}}}
        read.options["model_params"]["singer"]["sigma"] = 5.0
        read.options["models"].clear()
        assert await store.compare_and_set(dataclasses.replace(read, last_seq=1), expected_version=0)
        read.options["filter"] = "ukf"
        again = await store.get("s1")
        assert again.options == {"filter": "ckf", "models": [], "model_params": {"singer": {"sigma": 5.0}}}

    asyncio.run(scenario())


def test_a_batchs_fix_events_go_with_its_write_only_where_the_store_takes_them(store):
    """A store whose compare-and-set takes a batch's fix events (``fixes_in_write``, once its fix log is
    made) appends them exactly when the write applies, with the log's next ids; any other refuses them and
    writes nothing."""

    async def scenario() -> None:
        log = store.fix_log(100)
        await store.create(record(), max_sessions=10)
        current = await store.get("s1")
        applied = dataclasses.replace(current, last_seq=1)
        events = [NewFix("s1", "v-s1", "rsu_imu", 1.0 + k, b'{"k":%d}' % k) for k in range(3)]
        if not store.fixes_in_write:
            with pytest.raises(ValueError, match="apart"):
                await store.compare_and_set(applied, 0, events)
            assert (await store.get("s1")).version == 0
            return
        newest = await log.newest()
        assert not await store.compare_and_set(applied, 5, events)  # another version: nothing written
        assert await log.newest() == newest
        assert await store.compare_and_set(applied, 0, events)
        written = await log.read(newest, 0.05, 10)
        assert [(e.id, e.session_id, e.t, e.data) for e in written] == [
            (newest + 1 + k, "s1", 1.0 + k, b'{"k":%d}' % k) for k in range(3)
        ]
        assert (await store.get("s1")).last_seq == 1
        await log.close()

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
        # a read without the stored answer is the same record, the answer left out or not
        light = await store.get("s1", with_response=False)
        assert light in (
            dataclasses.replace(updated, version=1),
            dataclasses.replace(updated, version=1, last_response=None),
        )
        # a write from such a read stores the answer it carries
        assert await store.compare_and_set(dataclasses.replace(light, last_response=b'{"seq":2}'), 1)
        assert (await store.get("s1")).last_response == b'{"seq":2}'
        assert (await store.get("missing", with_response=False)) is None
        updated = dataclasses.replace(updated, last_response=b'{"seq":2}', version=2)
        # a second writer holding the old version loses
        assert not await store.compare_and_set(
            dataclasses.replace(updated, state=b"lost"), expected_version=1
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


def test_the_in_process_store_copies_a_record_as_dataclasses_replace_would():
    """MemoryStore copies a record through its ``__dict__``: the same record as ``dataclasses.replace``
    only while SessionRecord has no ``__post_init__`` and no field left out of ``__init__``."""
    assert not hasattr(SessionRecord, "__post_init__")
    assert all(field.init for field in dataclasses.fields(SessionRecord))
    original = record(options={"filter": "ckf", "models": ["ca", "at"], "model_params": {"at": {"tau": 2.0}}})
    copied = MemoryStore._copy(original, 7)
    assert type(copied) is SessionRecord and copied is not original
    assert copied == dataclasses.replace(original, version=7)
    assert copied.options is not original.options
    assert copied.options["models"] is not original.options["models"]
    assert MemoryStore._copy(original) == original
    with pytest.raises(dataclasses.FrozenInstanceError):
        copied.version = 8


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
        text = (
            "     3.04           N: GNSS NAV DATA    M: Mixed            RINEX VERSION / TYPE\n\u00b5 \n" * 3
        )
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


def test_base_stations_and_their_windows(store):
    async def scenario() -> None:
        assert await store.list_base_stations() == []
        assert await store.get_base_station("mare") is None
        assert await store.base_window("mare", 0.0, 10.0) is None
        assert await store.add_base_epochs("mare", [(1.0, "x")], 5) is None
        assert not await store.delete_base_station("mare")
        mare = StoredBaseStation("mare", '{"position": [1, 2, 3], "name": "\u00b5|x"}', 100.5)
        assert await store.add_base_station(mare)
        assert not await store.add_base_station(dataclasses.replace(mare, document="{}"))
        assert await store.get_base_station("mare") == mare
        assert not await store.replace_base_station(StoredBaseStation("other", "{}", 1.0))
        moved = dataclasses.replace(mare, document='{"position": null}', updated_at=101.0)
        assert await store.replace_base_station(moved)
        assert await store.add_base_station(StoredBaseStation("a-first", "{}", 1.0))
        assert [s.station_id for s in await store.list_base_stations()] == ["a-first", "mare"]
        # epochs: added out of order, one time twice (the later document wins), trimmed to the newest 4
        epochs = [(1290688800.0 + t, f"doc {t}|same") for t in (3.0, 1.0, 2.0, 5.5, 4.0)]
        assert await store.add_base_epochs("mare", epochs, 4) == 4
        assert await store.add_base_epochs("mare", [(1290688803.0, "replaced")], 4) == 4
        window = await store.base_window("mare", 1290688803.5, 1290688805.5)
        assert window == BaseWindow(
            moved,
            ((1290688803.0, "replaced"), (1290688804.0, "doc 4.0|same"), (1290688805.5, "doc 5.5|same")),
        )
        # nothing before 'since': only the epochs inside; an empty window of a registered station
        window = await store.base_window("mare", 1290688802.0, 1290688803.0)
        assert window is not None and window.epochs == (
            (1290688802.0, "doc 2.0|same"),
            (1290688803.0, "replaced"),
        )
        assert (await store.base_window("a-first", 0.0, 2e9)) == BaseWindow(
            StoredBaseStation("a-first", "{}", 1.0), ()
        )
        # deleting a station drops its window: a new one of the same id starts empty
        assert await store.delete_base_station("mare")
        assert await store.get_base_station("mare") is None
        assert await store.add_base_station(mare)
        assert (await store.base_window("mare", 0.0, 2e9)).epochs == ()

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


async def live(store: SessionStore, *vehicle_ids: str, now: float = 1000.0) -> dict[str, str]:
    """Open one session per vehicle (id ``s-<vehicle>``); returns vehicle id -> session id."""
    for vehicle_id in vehicle_ids:
        await store.create(record(f"s-{vehicle_id}", now=now, vehicle_id=vehicle_id), max_sessions=100)
    return {vehicle_id: f"s-{vehicle_id}" for vehicle_id in vehicle_ids}


def test_track_round_trips_exactly_and_replaces_whole(store):
    async def scenario() -> None:
        sessions = await live(store, "car", "bus")
        assert await store.get_tracks(["car", "bus"]) == {}
        assert await store.put_track(track("car", 3), sessions["car"])
        assert await store.put_track(track("bus", 1), sessions["bus"])
        got = await store.get_tracks(["car", "bus", "nobody"])
        assert got == {"car": track("car", 3), "bus": track("bus", 1)}
        assert await store.put_track(track("car", 2, t0=20.0), sessions["car"])
        assert (await store.get_tracks(["car"]))["car"] == track("car", 2, t0=20.0)
        assert await store.delete_track("car")
        assert not await store.delete_track("car")
        assert await store.get_tracks(["car"]) == {}

    asyncio.run(scenario())


def test_track_expires_with_the_session_ttl(store, clock):
    async def scenario() -> None:
        sessions = await live(store, "car")
        assert await store.put_track(track("car"), sessions["car"])
        clock.now += 59.0
        assert "car" in await store.get_tracks(["car"])
        clock.now += 2.0
        assert await store.get_tracks(["car"]) == {}

    asyncio.run(scenario())


def test_concurrent_track_writers_never_expose_a_mix(store):
    """Two vehicles publishing while a third reads: every read is one whole published track."""
    versions = {
        vehicle: [track(vehicle, count, t0=float(count)) for count in range(1, 12)] for vehicle in ("a", "b")
    }

    async def writer(vehicle: str) -> None:
        for version in versions[vehicle]:
            assert await store.put_track(version, f"s-{vehicle}")
            await asyncio.sleep(0)

    async def reader(seen: list[NeighbourTrack]) -> None:
        for _ in range(40):
            seen.extend((await store.get_tracks(["a", "b"])).values())
            await asyncio.sleep(0)

    async def scenario() -> list[NeighbourTrack]:
        await live(store, "a", "b")
        seen: list[NeighbourTrack] = []
        await asyncio.wait_for(asyncio.gather(writer("a"), writer("b"), reader(seen)), timeout=30)
        return seen

    for got in asyncio.run(scenario()):
        assert got in versions[got.vehicle_id]


# -- one live session per vehicle ------------------------------------------------------------------
KEY_1, KEY_2, KEY_3 = "k1" * 32, "k2" * 32, "k3" * 32
TOKEN_1, TOKEN_2 = "a1" * 32, "b2" * 32


def vehicle(vehicle_id: str, key_hash: str = KEY_1, created_at: float = 1000.125) -> VehicleRecord:
    return VehicleRecord(vehicle_id, key_hash, created_at, created_at + 0.5)


def test_a_new_session_supersedes_the_vehicles_live_one(store, clock):
    async def scenario() -> None:
        other = await live(store, "bus")
        assert await store.put_track(track("bus"), other["bus"])
        assert await store.create(record("s1", vehicle_id="car", token_hash=TOKEN_1), max_sessions=10) is None
        assert await store.live_session("car") == "s1"
        assert await store.put_track(track("car"), "s1")
        assert await store.count() == 2

        clock.now += 5.0
        superseded = await store.create(
            record("s2", now=clock.now, vehicle_id="car", token_hash=TOKEN_2), max_sessions=10
        )
        assert superseded == "s1"
        assert await store.get("s1") is None
        assert (await store.get("s2")).token_hash == TOKEN_2
        assert await store.live_session("car") == "s2"
        assert await store.count() == 2  # one went, one came
        assert await store.supersession("s1") == Supersession("s1", "s2", TOKEN_1, clock.now)
        assert await store.supersession("s2") is None
        assert await store.supersession("never") is None
        assert await store.get_tracks(["car", "bus"]) == {"bus": track("bus")}  # the old track is gone
        assert not await store.delete("s1")
        assert await store.live_session("bus") == "s-bus"  # other vehicles are untouched

        # remembered as long as an idle session would be, then forgotten
        clock.now += 60.0
        assert (await store.supersession("s1")).superseded_by == "s2"
        clock.now += 1.0
        assert await store.supersession("s1") is None
        await store.expire()
        assert await store.supersession("s1") is None

    asyncio.run(scenario())


def test_a_superseded_session_does_not_count_against_the_limit(store):
    async def scenario() -> None:
        await store.create(record("s1", vehicle_id="car"), max_sessions=1)
        assert await store.create(record("s2", vehicle_id="car"), max_sessions=1) == "s1"
        with pytest.raises(TooManySessions):
            await store.create(record("b1", vehicle_id="bus"), max_sessions=1)
        assert await store.get("b1") is None
        assert await store.live_session("bus") is None
        assert await store.count() == 1

        # a create refused by the limit supersedes nothing and deletes no track
        await store.create(record("b1", vehicle_id="bus"), max_sessions=2)
        assert await store.put_track(track("car"), "s2")
        with pytest.raises(TooManySessions):
            await store.create(record("s3", vehicle_id="car"), max_sessions=1)
        assert await store.live_session("car") == "s2"
        assert await store.get("s2") is not None
        assert await store.supersession("s2") is None
        assert await store.get("s3") is None
        assert "car" in await store.get_tracks(["car"])
        assert await store.count() == 2

    asyncio.run(scenario())


def test_an_expired_live_session_is_not_superseded(store, clock):
    async def scenario() -> None:
        await store.create(record("s1", vehicle_id="car"), max_sessions=1)
        clock.now += 61.0
        assert await store.live_session("car") is None
        assert await store.create(record("s2", now=clock.now, vehicle_id="car"), max_sessions=1) is None
        assert await store.supersession("s1") is None
        assert await store.live_session("car") == "s2"

    asyncio.run(scenario())


def test_only_the_live_session_may_publish_the_vehicles_track(store, clock):
    async def scenario() -> None:
        assert not await store.put_track(track("car"), "s1")  # no session at all
        assert await store.get_tracks(["car"]) == {}
        await store.create(record("s1", vehicle_id="car"), max_sessions=10)
        assert not await store.put_track(track("car"), "nobody")
        assert not await store.put_track(track("bus"), "s1")  # s1 is car's, not bus's
        assert await store.get_tracks(["car", "bus"]) == {}
        assert await store.put_track(track("car", 3), "s1")

        # superseded: its late write is refused and leaves the successor's track alone
        assert await store.create(record("s2", vehicle_id="car"), max_sessions=10) == "s1"
        assert await store.put_track(track("car", 2, t0=50.0), "s2")
        assert not await store.put_track(track("car", 5), "s1")
        assert (await store.get_tracks(["car"]))["car"] == track("car", 2, t0=50.0)

        # deleted: its pointer and track go with it, and it can publish nothing more
        assert await store.delete("s2")
        assert await store.live_session("car") is None
        assert await store.get_tracks(["car"]) == {}
        assert not await store.put_track(track("car"), "s2")
        assert await store.get_tracks(["car"]) == {}

        # expired: refused too
        await store.create(record("s3", vehicle_id="car"), max_sessions=10)
        clock.now += 61.0
        assert await store.get("s3") is None
        assert not await store.put_track(track("car"), "s3")
        assert await store.get_tracks(["car"]) == {}

    asyncio.run(scenario())


def test_delete_clears_the_pointer_and_track_only_of_the_live_session(store):
    async def scenario() -> None:
        await store.create(record("s1", vehicle_id="car"), max_sessions=10)
        assert await store.put_track(track("car"), "s1")
        assert await store.delete("s1")
        assert await store.live_session("car") is None
        assert await store.get_tracks(["car"]) == {}
        # nothing to supersede any more
        assert await store.create(record("s2", vehicle_id="car"), max_sessions=10) is None
        assert await store.supersession("s1") is None
        assert await store.put_track(track("car"), "s2")
        assert not await store.delete("s1")  # deleting it again touches nothing of s2
        assert await store.live_session("car") == "s2"
        assert "car" in await store.get_tracks(["car"])

    asyncio.run(scenario())


def test_concurrent_creates_for_one_vehicle_leave_one_live_session(store, handles):
    """Forty creates for one vehicle at once, spread over several handles (several workers where the
    store is shared): exactly one session is live, every other one was superseded exactly once."""
    ids = [f"c{i:02d}" for i in range(40)]

    async def scenario() -> None:
        results = await asyncio.gather(
            *(
                handles[i % len(handles)].create(
                    record(sid, vehicle_id="car", token_hash=f"{i:064x}"), max_sessions=5
                )
                for i, sid in enumerate(ids)
            )
        )
        alive = [sid for sid in ids if await store.get(sid) is not None]
        assert len(alive) == 1
        for handle in handles:
            assert await handle.live_session("car") == alive[0]
        assert await store.count() == 1
        assert results.count(None) == 1  # the first one superseded nothing
        assert sorted(sid for sid in results if sid is not None) == sorted(set(ids) - set(alive))
        successors = set()
        for i, sid in enumerate(ids):
            if sid in alive:
                continue
            entry = await store.supersession(sid)
            assert entry is not None and entry.token_hash == f"{i:064x}"
            successors.add(entry.superseded_by)
        assert alive[0] in successors and successors <= set(ids)

    asyncio.run(scenario())


def test_list_sessions_orders_pages_and_filters(store, clock):
    async def scenario() -> None:
        for i in (5, 1, 3, 2, 4):
            pipeline = "gnss" if i % 2 == 0 else "rsu_imu"
            await store.create(record(f"s{i}", vehicle_id=f"car{i}", pipeline=pipeline), max_sessions=10)

        def ids(page: list[SessionSummary]) -> list[str]:
            return [summary.session_id for summary in page]

        assert ids(await store.list_sessions()) == ["s1", "s2", "s3", "s4", "s5"]
        assert (await store.list_sessions(limit=1))[0] == SessionSummary.of(record("s1", vehicle_id="car1"))
        assert ids(await store.list_sessions(limit=2)) == ["s1", "s2"]
        assert ids(await store.list_sessions(after="s2", limit=2)) == ["s3", "s4"]
        assert ids(await store.list_sessions(after="s4", limit=2)) == ["s5"]
        assert ids(await store.list_sessions(after="s5")) == []
        assert ids(await store.list_sessions(after="s25")) == ["s3", "s4", "s5"]  # any string is a cursor
        assert ids(await store.list_sessions(pipeline="gnss")) == ["s2", "s4"]
        assert ids(await store.list_sessions(pipeline="gnss", after="s2")) == ["s4"]
        assert ids(await store.list_sessions(pipeline="nope")) == []
        assert ids(await store.list_sessions(vehicle_id="car3")) == ["s3"]
        assert ids(await store.list_sessions(vehicle_id="car3", after="s3")) == []
        assert ids(await store.list_sessions(vehicle_id="car3", pipeline="gnss")) == []
        assert ids(await store.list_sessions(vehicle_id="nobody")) == []

        # the summary follows the session's writes
        current = await store.get("s3")
        clock.now += 30.0
        written = dataclasses.replace(
            current, last_seq=4, batches=2, epochs=9, last_fix='{"t":3.5}', updated_at=clock.now, state=b"x"
        )
        assert await store.compare_and_set(written, 0)
        assert await store.list_sessions(vehicle_id="car3") == [SessionSummary.of(written)]

        # superseded and expired sessions are not listed
        assert await store.create(record("s6", now=clock.now, vehicle_id="car4"), max_sessions=10) == "s4"
        assert ids(await store.list_sessions()) == ["s1", "s2", "s3", "s5", "s6"]
        assert ids(await store.list_sessions(vehicle_id="car4")) == ["s6"]
        clock.now += 31.0  # the untouched ones are idle 61 s now
        assert ids(await store.list_sessions()) == ["s3", "s6"]
        assert ids(await store.list_sessions(vehicle_id="car1")) == []

    asyncio.run(scenario())


def test_list_sessions_pages_through_many(store):
    async def scenario() -> None:
        for i in range(130):
            pipeline = "gnss" if i % 3 == 0 else "rsu_imu"
            await store.create(record(f"m{i:03d}", pipeline=pipeline), max_sessions=1000)
        seen: list[str] = []
        after = None
        while True:
            page = await store.list_sessions(after=after, limit=7, pipeline="gnss")
            if not page:
                break
            assert len(page) <= 7
            seen.extend(summary.session_id for summary in page)
            after = page[-1].session_id
        assert seen == [f"m{i:03d}" for i in range(0, 130, 3)]

    asyncio.run(scenario())


# -- the vehicle registry ---------------------------------------------------------------------------
def test_vehicle_registry_adds_gets_lists_and_counts(store):
    async def scenario() -> None:
        assert await store.count_vehicles() == 0
        assert await store.list_vehicles() == []
        first = [
            vehicle("b", "kb" * 32),
            vehicle("a", "ka" * 32, created_at=1000.1234567891),
            vehicle("c", "kc" * 32),
        ]
        assert await store.add_vehicles(first) == ["b", "a", "c"]
        # registered ones are kept as they are (their keys are not replaced), new ones are added
        again = [vehicle("a", "zz" * 32), vehicle("d", "kd" * 32), vehicle("d", "ye" * 32), first[0]]
        assert await store.add_vehicles(again) == ["d"]
        assert await store.add_vehicles([]) == []
        assert await store.count_vehicles() == 4
        assert await store.get_vehicle("a") == first[1]  # floats round-trip exactly
        assert await store.get_vehicle("d") == vehicle("d", "kd" * 32)
        assert await store.get_vehicle("zz") is None
        assert await store.vehicle_of_key("ka" * 32) == "a"
        assert await store.vehicle_of_key("kd" * 32) == "d"
        assert await store.vehicle_of_key("zz" * 32) is None
        assert await store.vehicle_of_key("ye" * 32) is None
        everyone = sorted([*first, vehicle("d", "kd" * 32)], key=lambda v: v.vehicle_id)
        assert await store.list_vehicles() == everyone
        assert [v.vehicle_id for v in await store.list_vehicles(limit=2)] == ["a", "b"]
        assert [v.vehicle_id for v in await store.list_vehicles(after="b", limit=2)] == ["c", "d"]
        assert [v.vehicle_id for v in await store.list_vehicles(after="bb")] == ["c", "d"]
        assert await store.list_vehicles(after="d") == []

    asyncio.run(scenario())


def test_vehicle_list_pages_through_many(store):
    async def scenario() -> None:
        many = [vehicle(f"veh{i:04d}", f"{i:064x}", created_at=1000.0 + i / 7) for i in range(250)]
        assert len(await store.add_vehicles(list(reversed(many)))) == 250
        assert await store.count_vehicles() == 250
        seen: list[VehicleRecord] = []
        after = None
        while page := await store.list_vehicles(after=after, limit=100):
            seen.extend(page)
            after = page[-1].vehicle_id
        assert seen == many

    asyncio.run(scenario())


def test_rotating_a_vehicle_key_retires_the_old_one(store):
    async def scenario() -> None:
        await store.add_vehicles([vehicle("car", KEY_1, created_at=1712345678.1234567)])
        await store.create(record("s1", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_1)
        rotated = await store.rotate_vehicle_key("car", KEY_2, 1712349999.9876543)
        assert rotated == VehicleRecord("car", KEY_2, 1712345678.1234567, 1712349999.9876543)  # exact floats
        assert await store.get_vehicle("car") == rotated
        assert await store.vehicle_of_key(KEY_1) is None
        assert await store.vehicle_of_key(KEY_2) == "car"
        assert await store.count_vehicles() == 1
        assert await store.rotate_vehicle_key("nobody", KEY_3, 2001.0) is None
        assert await store.vehicle_of_key(KEY_3) is None
        assert await store.live_session("car") == "s1"  # the live session keeps running
        with pytest.raises(VehicleNotRegistered):
            await store.create(record("s2", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_1)
        assert await store.live_session("car") == "s1"
        renewed = await store.create(record("s2", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_2)
        assert renewed == "s1"

    asyncio.run(scenario())


def test_create_with_a_vehicle_key_opens_nothing_unless_the_key_is_current(store):
    async def scenario() -> None:
        with pytest.raises(VehicleNotRegistered) as refused:
            await store.create(record("x1", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_1)
        assert refused.value.vehicle_id == "car"
        assert await store.get("x1") is None and await store.count() == 0
        assert await store.live_session("car") is None

        await store.add_vehicles([vehicle("car", KEY_1), vehicle("bus", KEY_2)])
        await store.create(record("s1", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_1)
        assert await store.put_track(track("car"), "s1")
        for key_hash in (KEY_2, KEY_3):  # another vehicle's key, an unknown key
            with pytest.raises(VehicleNotRegistered):
                await store.create(record("x2", vehicle_id="car"), max_sessions=10, vehicle_key_hash=key_hash)
        # nothing written: no session, nothing superseded, the track kept
        assert await store.get("x2") is None
        assert await store.live_session("car") == "s1"
        assert await store.supersession("s1") is None
        assert "car" in await store.get_tracks(["car"])
        assert await store.count() == 1

        await store.rotate_vehicle_key("car", KEY_3, 1500.0)
        with pytest.raises(VehicleNotRegistered):
            await store.create(record("x3", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_1)
        await store.delete_vehicle("car")
        with pytest.raises(VehicleNotRegistered):
            await store.create(record("x4", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_3)
        assert await store.get("x3") is None and await store.get("x4") is None
        assert await store.count() == 0
        # without a vehicle key the registry is not consulted
        assert await store.create(record("s5", vehicle_id="car"), max_sessions=10) is None

    asyncio.run(scenario())


def test_a_key_hash_belongs_to_one_vehicle_only(store):
    """Registering or rotating to a key hash another vehicle has is refused and writes nothing."""

    async def scenario() -> None:
        await store.add_vehicles([vehicle("car", KEY_1)])
        taken = [vehicle("bus", KEY_2), vehicle("van", KEY_1)]
        twice = [vehicle("bus", KEY_2), vehicle("van", KEY_2)]
        for batch in (taken, twice):
            with pytest.raises(ValueError):
                await store.add_vehicles(batch)
            assert await store.get_vehicle("bus") is None  # nothing of the batch was added
            assert await store.vehicle_of_key(KEY_1) == "car" and await store.vehicle_of_key(KEY_2) is None
        assert await store.add_vehicles([vehicle("bus", KEY_2)]) == ["bus"]
        with pytest.raises(ValueError):
            await store.rotate_vehicle_key("bus", KEY_1, 2000.0)
        assert await store.get_vehicle("bus") == vehicle("bus", KEY_2)
        assert await store.vehicle_of_key(KEY_1) == "car" and await store.vehicle_of_key(KEY_2) == "bus"
        assert (await store.rotate_vehicle_key("bus", KEY_2, 2001.0)).key_issued_at == 2001.0  # its own key
        assert await store.vehicle_of_key(KEY_2) == "bus"

    asyncio.run(scenario())


def test_deleting_a_vehicle_revokes_it_and_ends_its_live_session(store):
    async def scenario() -> None:
        await store.add_vehicles([vehicle("car", KEY_1), vehicle("bus", KEY_2), vehicle("van", KEY_3)])
        await store.create(record("s1", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_1)
        await store.create(record("b1", vehicle_id="bus"), max_sessions=10, vehicle_key_hash=KEY_2)
        assert await store.put_track(track("car"), "s1")
        assert await store.put_track(track("bus"), "b1")

        assert await store.delete_vehicle("car") == Revocation("car", "s1")
        assert await store.get("s1") is None
        assert await store.live_session("car") is None
        assert await store.supersession("s1") is None  # revoked, not superseded
        assert await store.get_tracks(["car", "bus"]) == {"bus": track("bus")}
        assert await store.get_vehicle("car") is None
        assert await store.vehicle_of_key(KEY_1) is None
        assert await store.count_vehicles() == 2
        assert await store.count() == 1
        assert not await store.put_track(track("car"), "s1")
        assert await store.delete_vehicle("car") is None
        assert await store.delete_vehicle("nobody") is None

        assert await store.delete_vehicle("van") == Revocation("van", None)  # no live session
        assert await store.live_session("bus") == "b1"
        assert await store.vehicle_of_key(KEY_2) == "bus"
        assert [v.vehicle_id for v in await store.list_vehicles()] == ["bus"]

    asyncio.run(scenario())


# -- request-rate limits: a look that uses nothing --------------------------------------------------
def test_request_wait_uses_no_budget(store, clock):
    limit = RateLimit(rate_per_s=5.0, burst=3)

    async def scenario() -> None:
        assert [await store.request_wait("k", limit) for _ in range(20)] == [0.0] * 20
        assert [await store.take_request("k", limit) for _ in range(3)] == [0.0, 0.0, 0.0]
        for _ in range(10):
            assert await store.request_wait("k", limit) == pytest.approx(0.2)
        assert await store.take_request("k", limit) == pytest.approx(0.2)
        clock.now += 0.1
        assert await store.request_wait("k", limit) == pytest.approx(0.1)
        clock.now += 0.1
        assert [await store.request_wait("k", limit) for _ in range(10)] == [0.0] * 10
        assert await store.take_request("k", limit) == 0.0
        assert await store.request_wait("k", limit) == pytest.approx(0.2)
        assert await store.request_wait("other", limit) == 0.0

    asyncio.run(scenario())


# -- the SQLite file of an earlier version -----------------------------------------------------------
def test_sqlite_file_of_an_earlier_version_is_upgraded(tmp_path, clock):
    """A file written before the vehicle registry existed opens, keeps its sessions and gains the
    new tables."""
    path = tmp_path / "old.db"
    old = sqlite3.connect(path)
    old.executescript(
        """
        CREATE TABLE sessions (
            session_id TEXT PRIMARY KEY, vehicle_id TEXT NOT NULL, pipeline TEXT NOT NULL,
            options TEXT NOT NULL, token_hash TEXT NOT NULL, state BLOB NOT NULL,
            created_at REAL NOT NULL, updated_at REAL NOT NULL, last_seq INTEGER NOT NULL,
            last_request_hash TEXT, last_response BLOB, batches INTEGER NOT NULL,
            epochs INTEGER NOT NULL, last_fix TEXT, version INTEGER NOT NULL
        );
        CREATE TABLE tracks (vehicle_id TEXT PRIMARY KEY, written_at REAL NOT NULL, track TEXT NOT NULL);
        CREATE TABLE rate_limits (key TEXT PRIMARY KEY, tat REAL NOT NULL);
        INSERT INTO sessions VALUES ('old', 'car', 'rsu_imu', '{}', 'h', x'00', 1000.0, 1000.0, 0,
                                     NULL, NULL, 0, 0, NULL, 0);
        """
    )
    old.close()
    store = SQLiteStore(path, 60.0, clock)

    async def scenario() -> None:
        assert (await store.get("old")).vehicle_id == "car"
        assert await store.live_session("car") is None  # opened before pointers existed
        assert await store.add_vehicles([vehicle("car", KEY_1)]) == ["car"]
        opened = await store.create(record("new", vehicle_id="car"), max_sessions=10, vehicle_key_hash=KEY_1)
        assert opened is None
        assert await store.live_session("car") == "new"
        assert [s.session_id for s in await store.list_sessions()] == ["new", "old"]
        await store.close()

    asyncio.run(scenario())


def test_documents_by_kind(store):
    async def scenario() -> None:
        assert await store.list_documents("zones") == {}
        assert await store.get_document("zones", "a") is None
        assert not await store.replace_document("zones", "a", "{}")
        assert await store.get_document("zones", "a") is None  # replace never creates
        await store.put_document("zones", "b", '{"r": 2}')
        await store.put_document("zones", "a", '{"r": "\u00b5"}')
        await store.put_document("subscriptions", "a", "other kind")
        assert await store.list_documents("zones") == {"a": '{"r": "\u00b5"}', "b": '{"r": 2}'}
        assert list(await store.list_documents("zones")) == ["a", "b"]
        assert await store.replace_document("zones", "b", '{"r": 3}')
        assert await store.get_document("zones", "b") == '{"r": 3}'
        assert await store.delete_document("zones", "b")
        assert not await store.delete_document("zones", "b")
        assert not await store.replace_document("zones", "b", '{"r": 4}')
        assert await store.list_documents("zones") == {"a": '{"r": "\u00b5"}'}
        assert await store.get_document("subscriptions", "a") == "other kind"

    asyncio.run(scenario())


def test_a_lease_has_one_holder_until_it_runs_out(store, clock):
    async def scenario() -> None:
        assert await store.acquire_lease("notifier", "worker-1", 0.3)
        assert not await store.acquire_lease("notifier", "worker-2", 0.3)
        assert await store.acquire_lease("notifier", "worker-1", 0.3)  # renewed by its holder
        assert await store.acquire_lease("other", "worker-2", 0.3)  # leases are independent
        clock.now += 0.5
        await asyncio.sleep(0.5)  # a store that keeps time itself (Redis) sees it run out too
        assert await store.acquire_lease("notifier", "worker-2", 0.3)
        assert not await store.acquire_lease("notifier", "worker-1", 0.3)

    asyncio.run(scenario())
