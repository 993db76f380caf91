"""The fix stream's log on every store (memory, SQLite, Redis, Redis Cluster): dense ids, a blocking read
that returns what was appended after its id, a backlog that is exactly the events after an id, and the gap
(how many were missed) once the bounded buffer no longer holds them."""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest
from edgepos.store import open_store
from edgepos.store.base import SessionStore
from edgepos.store.fixlog import FixLog, MemoryFixLog, NewFix, gap_between, parse_event_id
from edgepos.store.memory import AppendedFixLog
from hypothesis import given, settings
from hypothesis import strategies as st

_prefixes = itertools.count()


@pytest.fixture(params=["memory", "sqlite", "redis", "redis-cluster"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[SessionStore]:
    kind = request.param
    if kind == "memory":
        url = "memory"
    elif kind == "sqlite":
        url = f"sqlite:///{tmp_path}/store.db"
    elif kind == "redis":
        url = request.getfixturevalue("redis_server").url(f"fixlog{next(_prefixes)}:")
    else:
        url = request.getfixturevalue("redis_cluster").url(f"fixlog{next(_prefixes)}:")
    store = open_store(url, 3600.0)
    yield store
    asyncio.run(store.close())


def _fixes(count: int, vehicle: str = "car-1") -> list[NewFix]:
    return [NewFix("s1", vehicle, "rsu_imu", 0.05 * (n + 1), b'{"n":%d}' % n) for n in range(count)]


async def _exercise(log: FixLog) -> None:
    assert await log.newest() == 0
    assert await log.read(0, 0.05, 10) == []  # nothing yet: waits, then empty
    assert await log.backlog(0) == ([], None)
    await log.append(_fixes(3))
    assert await log.newest() == 3
    read = await log.read(0, 1.0, 10)
    assert [e.id for e in read] == [1, 2, 3]
    assert [e.data for e in read] == [b'{"n":0}', b'{"n":1}', b'{"n":2}']
    assert (read[0].session_id, read[0].vehicle_id, read[0].pipeline, read[0].t) == (
        "s1",
        "car-1",
        "rsu_imu",
        0.05,
    )
    assert [e.id for e in await log.read(1, 1.0, 1)] == [2]
    # a reader blocked on the newest id gets what is appended while it waits
    waiting = asyncio.create_task(log.read(3, 5.0, 10))
    await asyncio.sleep(0.1)
    await log.append(_fixes(2, "car-2"))
    assert [(e.id, e.vehicle_id) for e in await waiting] == [(4, "car-2"), (5, "car-2")]
    events, gap = await log.backlog(2)
    assert gap is None and [e.id for e in events] == [3, 4, 5]
    # past the buffer (10 events; Redis trims whole nodes of 100 entries, so to about that): the gap says
    # exactly how many were missed
    await log.append(_fixes(300))
    events, gap = await log.backlog(1)
    assert gap is not None and gap.reason == "trimmed"
    oldest = events[0].id
    assert gap.oldest_id == oldest and gap.missed == oldest - 2
    assert [e.id for e in events] == list(range(oldest, 306))
    assert 10 <= len(events) <= 200
    events, gap = await log.backlog(1000)  # ahead of the log: unknown, everything held is given
    assert gap is not None and gap.reason == "unknown" and gap.missed is None and events[-1].id == 305
    await log.close()


def test_the_fix_log_contract(store: SessionStore):
    async def run() -> None:
        await _exercise(store.fix_log(10))
        await store.close()

    asyncio.run(run())


def test_event_ids_and_gaps():
    assert parse_event_id("17") == 17 and parse_event_id("17-0") == 17
    for bad in ("", "x", "-1", "1-1", "1.5", "9" * 25):
        with pytest.raises(ValueError):
            parse_event_id(bad)
    assert gap_between(5, 6, 10) is None
    assert gap_between(3, 6, 10) == gap_between(3, 6, 10) and gap_between(3, 6, 10).missed == 2
    assert gap_between(11, 6, 10).reason == "unknown"
    assert gap_between(0, None, 0) is None


def test_the_stream_hub_delivers_through_every_store(store: SessionStore):
    """The service's side (publisher, reader, a consumer's events) over each store's log, the cluster's too."""
    from edgepos.api.metrics import Metrics
    from edgepos.api.streams import StreamFilter, StreamHub

    async def run() -> bytes:
        hub = StreamHub(store.fix_log(100), Metrics(), queue=100, max_consumers=4, ping_s=0.2, interval_s=0.0)
        consumer, backlog, gap = await hub.subscribe(StreamFilter(vehicles=frozenset({"car-2"})), None)
        events = hub.events(consumer, backlog, gap, None, None)
        received = await anext(events)  # the preamble
        hub.publish(_fixes(3, "car-1") + _fixes(2, "car-2"))
        for _ in range(100):  # pings (every 0.2 s) bound the wait
            if received.count(b"event: fix") >= 2:
                break
            received += await anext(events)
        await events.aclose()
        await hub.close()
        await store.close()
        return received

    received = asyncio.run(run())
    assert received.count(b"event: fix") == 2
    assert b'id: 4\nevent: fix\ndata: {"n":0}' in received and b'id: 5\nevent: fix\ndata: {"n":1}' in received


def test_the_hub_appends_to_the_in_process_log_as_it_publishes():
    """No publisher task for the in-process store's log: the fixes are in it, in order, once published."""
    from edgepos.api.metrics import Metrics
    from edgepos.api.streams import StreamHub
    from edgepos.store.memory import MemoryStore

    async def run() -> None:
        log = MemoryStore(3600.0).fix_log(100)
        hub = StreamHub(log, Metrics(), queue=10, max_consumers=1, ping_s=1.0)
        hub.publish(_fixes(3))
        hub.publish(_fixes(2, "car-2"))
        assert await log.newest() == 5  # awaiting a call that does not suspend: no other task ran
        events = await log.read(0, 0.0, 10)
        assert [(e.id, e.vehicle_id, e.data) for e in events] == [
            (1, "car-1", b'{"n":0}'),
            (2, "car-1", b'{"n":1}'),
            (3, "car-1", b'{"n":2}'),
            (4, "car-2", b'{"n":0}'),
            (5, "car-2", b'{"n":1}'),
        ]
        await hub.close()

    asyncio.run(run())


_OPERATIONS = st.lists(
    st.one_of(
        st.tuples(st.just("append"), st.integers(0, 25)),
        st.tuples(st.just("read"), st.integers(-2, 80), st.integers(1, 30)),
        st.tuples(st.just("backlog"), st.integers(-2, 80)),
        st.tuples(st.just("newest")),
    ),
    max_size=40,
)


@settings(max_examples=200, deadline=None)
@given(buffer=st.integers(1, 12), operations=_OPERATIONS)
def test_the_in_process_store_log_answers_as_the_memory_log(buffer: int, operations: list[tuple]):
    """The in-process store's log (fixes held as appended, events made when read) gives the very events,
    gaps and ids of :class:`MemoryFixLog` after any appends (reads not blocking)."""

    async def answers(log: FixLog) -> list[object]:
        out: list[object] = []
        appended = 0
        for operation in operations:
            if operation[0] == "append":
                await log.append(_fixes(operation[1], f"car-{appended}"))
                appended += 1
            elif operation[0] == "read":
                out.append(await log.read(operation[1], 0.0, operation[2]))
            elif operation[0] == "backlog":
                out.append(await log.backlog(operation[1]))
            else:
                out.append(await log.newest())
        return out

    expected = asyncio.run(answers(MemoryFixLog(buffer)))
    assert asyncio.run(answers(AppendedFixLog(buffer))) == expected
