"""The fix stream's Redis layout (``store.redis_fix_entries``): one entry per run of consecutive fixes of a
session, which gives back exactly the fixes appended, with dense ids, however a read or a backlog falls
inside an entry."""

from __future__ import annotations

import asyncio
import itertools
from typing import Any

import pytest
import redis
from edgepos.store import open_store
from edgepos.store.fixlog import FixEvent, NewFix
from edgepos.store.redis_fix_entries import (
    ARGUMENTS_PER_ENTRY,
    FIXES_PER_ENTRY,
    entry_events,
    fix_arguments,
)
from hypothesis import given
from hypothesis import strategies as st

RedisServer = Any  # tests/store/conftest.py's RedisServer (conftest modules are not importable by name)

_prefixes = itertools.count()
_FIELDS = (b"s", b"v", b"p", b"n", b"t", b"l", b"d")


def _entries(fixes: list[NewFix]) -> list[tuple[str, dict[bytes, bytes]]]:
    """The entries the scripts would write for ``fixes`` (ids from 1), built from ``fix_arguments``."""
    arguments = [value if isinstance(value, bytes) else value.encode() for value in fix_arguments(fixes)]
    entries, last = [], 0
    for start in range(0, len(arguments), ARGUMENTS_PER_ENTRY):
        fields = dict(zip(_FIELDS, arguments[start : start + ARGUMENTS_PER_ENTRY], strict=True))
        last += int(fields[b"n"])
        entries.append((f"{last}-0", fields))
    return entries


def _fix(session: str, t: float, data: bytes) -> NewFix:
    return NewFix(session, f"car-{session}", "rsu_imu", t, data)


_new_fixes = st.lists(
    st.builds(
        _fix,
        st.sampled_from(["a", "b"]),
        st.floats(allow_nan=False, allow_infinity=False),
        st.binary(max_size=40),  # any bytes: spaces, newlines, nothing
    ),
    max_size=250,
)


@given(_new_fixes)
def test_the_entries_give_back_every_fix_with_dense_ids(fixes: list[NewFix]):
    entries = _entries(fixes)
    events = [event for entry in entries for event in entry_events(*entry)]
    expected = [
        FixEvent(n + 1, fix.session_id, fix.vehicle_id, fix.pipeline, fix.t, fix.data)
        for n, fix in enumerate(fixes)
    ]
    assert events == expected
    # one entry per run of one session's fixes, none longer than the cap
    runs = [len(list(run)) for _, run in itertools.groupby(fixes, key=lambda fix: fix.session_id)]
    assert len(entries) == sum(-(-run // FIXES_PER_ENTRY) for run in runs)


def test_a_batch_is_one_entry_and_a_long_run_is_cut():
    batch = [_fix("a", 0.05 * n, b'{"n":%d}' % n) for n in range(20)]
    assert len(fix_arguments(batch)) == ARGUMENTS_PER_ENTRY
    assert fix_arguments(batch)[:5] == [
        "a",
        "car-a",
        "rsu_imu",
        "20",
        " ".join(repr(0.05 * n) for n in range(20)),
    ]
    long_run = [_fix("a", float(n), b"x") for n in range(2 * FIXES_PER_ENTRY + 1)]
    assert [fields[b"n"] for _, fields in _entries(long_run)] == [b"100", b"100", b"1"]


def test_an_entry_not_of_this_layout_is_refused():
    ((entry_id, fields),) = _entries([_fix("a", 1.0, b"ab"), _fix("a", 2.0, b"c")])
    with pytest.raises(ValueError, match="says 3 fixes but holds 2"):
        entry_events(entry_id, {**fields, b"n": b"3"})
    with pytest.raises(ValueError, match="sum of its fixes' lengths"):
        entry_events(entry_id, {**fields, b"d": b"abcd"})


def test_the_redis_stream_holds_an_entry_per_run_and_reads_split_them(redis_server: RedisServer):
    prefix = f"fixentries{next(_prefixes)}:"
    store = open_store(redis_server.url(prefix), 3600.0)
    client = redis.Redis(port=redis_server.port)

    async def exercise() -> None:
        log = store.fix_log(30)
        fixes = [_fix("a", 1.0, b"a1"), _fix("a", 2.0, b"a2"), _fix("b", 1.5, b"b1"), _fix("a", 3.0, b"a3")]
        await log.append(fixes)
        assert client.xlen(f"{prefix}{{fixes}}:entries") == 3  # a a | b | a
        events = await log.read(0, 1.0, 10)
        assert [(e.id, e.session_id, e.data) for e in events] == [
            (n + 1, fix.session_id, fix.data) for n, fix in enumerate(fixes)
        ]
        # a read from inside an entry gives what follows, up to the count
        assert [e.id for e in await log.read(1, 1.0, 2)] == [2, 3]
        events, gap = await log.backlog(1)
        assert gap is None and [e.id for e in events] == [2, 3, 4]
        # 20-fix batches with a buffer of 30: whole entries go once all their fixes are older than it
        for batch in range(5):
            await log.append([_fix("a", 10.0 * batch + n, b"x") for n in range(20)])
        events, gap = await log.backlog(0)
        assert gap is not None and gap.reason == "trimmed"
        assert [e.id for e in events] == list(range(65, 105))  # the last two entries: 40 fixes
        assert gap.missed == 64 and client.xlen(f"{prefix}{{fixes}}:entries") == 2
        await log.close()
        await store.close()

    asyncio.run(exercise())
    client.close()
