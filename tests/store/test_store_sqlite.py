"""The SQLite store shared by several processes: no lost updates, nothing seen half-written."""

from __future__ import annotations

import asyncio
import dataclasses
import multiprocessing
import sqlite3
import time
from pathlib import Path

from edgepos.store import SessionRecord, SQLiteStore

INCREMENTS = 40


def _increment(path: str, session_id: str, count: int) -> int:
    """A worker process: add 1 to ``batches`` ``count`` times by load + compare-and-set + retry."""

    async def work() -> int:
        store = SQLiteStore(path, 3600.0)
        conflicts = 0
        for _ in range(count):
            while True:
                current = await store.get(session_id)
                assert current is not None
                updated = dataclasses.replace(
                    current, batches=current.batches + 1, state=current.state + b"+"
                )
                if await store.compare_and_set(updated, current.version):
                    break
                conflicts += 1
        await store.close()
        return conflicts

    return asyncio.run(work())


def test_concurrent_processes_lose_no_update(tmp_path: Path):
    path = str(tmp_path / "shared.db")
    store = SQLiteStore(path, 3600.0)
    now = time.time()
    record = SessionRecord("s", "car", "rsu_imu", {}, "h", b"", now, now)
    asyncio.run(store.create(record, max_sessions=10))
    context = multiprocessing.get_context("spawn")
    with context.Pool(3) as pool:
        pool.starmap(_increment, [(path, "s", INCREMENTS)] * 3)
    final = asyncio.run(store.get("s"))
    asyncio.run(store.close())
    assert final is not None
    assert final.batches == 3 * INCREMENTS
    assert final.version == 3 * INCREMENTS
    assert final.state == b"+" * (3 * INCREMENTS)


def test_two_store_objects_see_each_others_writes(tmp_path: Path):
    path = tmp_path / "two.db"

    async def scenario() -> None:
        first, second = SQLiteStore(path, 3600.0), SQLiteStore(path, 3600.0)
        now = time.time()
        await first.create(SessionRecord("s", "car", "rsu_imu", {"a": [1, 2.5]}, "h", b"x", now, now), 5)
        seen = await second.get("s")
        assert seen is not None and seen.options == {"a": [1, 2.5]}
        assert await second.compare_and_set(dataclasses.replace(seen, state=b"y"), 0)
        assert not await first.compare_and_set(dataclasses.replace(seen, state=b"z"), 0)
        assert (await first.get("s")).state == b"y"
        assert await second.count() == 1
        await first.close()
        await second.close()

    asyncio.run(scenario())


def test_database_uses_wal(tmp_path: Path):
    store = SQLiteStore(tmp_path / "wal.db", 60.0)
    asyncio.run(store.count())
    asyncio.run(store.close())
    mode = sqlite3.connect(tmp_path / "wal.db").execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"
