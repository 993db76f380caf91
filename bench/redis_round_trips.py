"""Benchmark: Redis round trips per ``rsu_imu`` batch, counted in the client (the latency a batch waits on).

A command is one round trip; a pipeline or transaction is one round trip however many commands it holds.
Starts ``redis-server`` on loopback, builds the service in this process on it (``create_app``, the
paper scenario's RSU map), opens ``--vehicles`` sessions and sends each ``--batches`` 20-epoch batches
with its session token, counting every await on the Redis client (``execute_command`` and pipeline
``execute``, patched) by command name. The fix stream's appends run in the worker's publisher task, off
the answer's path, shared by the batches that arrive together: they are counted apart. Also prints the
median answer time of a batch and this process's CPU per batch (one request at a time; the Redis
server's CPU is not in it), and with ``--memory`` the same on the in-process store for comparison.
Last, timed alone on this process's event loop: the two reads a batch on a cached record skips (the
token check's ``HMGET`` of a 20 kB state, the RSUs' ``HMGET``), wall and CPU time per batch; and what a
batch's answer and fixes cost this process on Redis (the compare-and-set's pipeline and a 20-fix append
to the fix stream, on a record of the run: its state, stored answer and last fix), thread CPU per batch.

    python bench/redis_round_trips.py [--batches 20] [--vehicles 2] [--rate-limit 0] [--memory]
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import hashlib
import os
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from edgepos.loadgen import common
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.pipelines.base import Rsu
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs
from edgepos.store import redis_round_trip
from edgepos.store.base import SessionRecord
from edgepos.store.fixlog import NewFix
from edgepos.store.redis import RedisStore
from fastapi.testclient import TestClient
from redis.asyncio.client import Pipeline, Redis

ADMIN_KEY = "round-trip-bench-" + os.urandom(8).hex()
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}


class RoundTrips:
    """Counts the Redis client's round trips by what they carry (patched into redis-py's asyncio client and
    the store's own round trips)."""

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.counting = False

    def install(self) -> None:
        command, execute = Redis.execute_command, Pipeline.execute
        counter = self

        async def counted_command(client: Any, *args: Any, **options: Any) -> Any:
            if counter.counting:
                counter.counts[_name(args)] += 1
            return await command(client, *args, **options)

        async def counted_execute(pipe: Any, *args: Any, **options: Any) -> Any:
            if counter.counting:
                names = "+".join(_name(c[0]) for c in pipe.command_stack)
                counter.counts[f"pipeline[{names}]"] += 1
            return await execute(pipe, *args, **options)

        exchange = redis_round_trip._exchange

        async def counted_exchange(connection: Any, commands: Any) -> Any:
            # the store's own round trips (store.redis_round_trip: the compare-and-set, the scripts, the
            # fix log's appends) go to a pooled connection directly, past the client's methods above
            if counter.counting:
                names = "+".join(_name(c) for c in commands)
                counter.counts[f"round_trip[{names}]" if len(commands) > 1 else names] += 1
            return await exchange(connection, commands)

        Redis.execute_command = counted_command  # type: ignore[method-assign]
        Pipeline.execute = counted_execute  # type: ignore[method-assign]
        redis_round_trip._exchange = counted_exchange  # type: ignore[assignment]


_SCRIPTS = {hashlib.sha1(source.encode()).hexdigest(): name for name, source in RedisStore.SCRIPTS.items()}


def _name(args: Any) -> str:
    """The command's name; for EVALSHA, the store's name of the script too."""
    name = str(args[0]).upper() if args else "?"
    if name == "EVALSHA" and len(args) > 1:
        name += f"({_SCRIPTS.get(str(args[1]), '?')})"
    return name


def _wire(observation: Any) -> dict[str, Any]:
    """An observation as a batch's JSON measurement (the load generator's own conversion)."""
    wire: dict[str, Any] = common.to_wire(observation).model_dump(mode="json", exclude_none=True)
    return wire


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, default=20, help="batches per vehicle")
    parser.add_argument("--vehicles", type=int, default=2)
    parser.add_argument("--rate-limit", type=float, default=0.0, help="EDGEPOS_RATE_LIMIT_PER_S (0: off)")
    parser.add_argument("--memory", action="store_true", help="time the in-process store too")
    args = parser.parse_args()
    binary = redis_binary()
    if binary is None:
        print("redis-server is not installed (apt-get install -y redis-server)", file=sys.stderr)
        return 2
    scenario = rsu_imu_paper_scenario()
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(7))
    rsus = {"rsus": [r.model_dump(mode="json", exclude_none=True) for r in common.scenario_rsus(scenario)]}
    bodies = [
        {"seq": seq, "measurements": [_wire(o) for e in epochs[(seq - 1) * 20 : seq * 20] for o in e]}
        for seq in range(1, args.batches + 1)
    ]
    counter = RoundTrips()
    counter.install()
    print(f"load average {os.getloadavg()[0]:.2f}", flush=True)
    with (
        tempfile.TemporaryDirectory(prefix="edgepos-rt-") as tmp,
        RedisServer(binary, Path(tmp) / "redis", "--save", "", "--appendonly", "no") as server,
    ):
        stores = {"redis": server.url("rt:")} | ({"memory": "memory"} if args.memory else {})
        for name, store in stores.items():
            settings = Settings(
                admin_key=ADMIN_KEY,
                admin_key_file=Path(tmp) / f"{name}.key",
                store=store,
                rate_limit_per_s=args.rate_limit,
                log_level="warning",
            )
            times, cpu = _drive(settings, rsus, bodies, args.vehicles, counter if name == "redis" else None)
            print(
                f"{name:6s} rsu_imu, {len(times)} batches of 20 epochs one at a time, rate limit "
                f"{args.rate_limit:g}/s: answer {statistics.median(times) * 1e3:.2f} ms median, service CPU "
                f"{cpu / len(times) * 1e3:.2f} ms per batch",
                flush=True,
            )
            if name == "redis":
                total = sum(counter.counts.values())
                print(f"       {total / len(times):.2f} Redis round trips per batch in all:")
                for command, count in counter.counts.most_common():
                    print(f"         {count / len(times):5.2f} per batch  {command}")
        wall, cpu = asyncio.run(_skipped_reads(server.url("skip:"), [r.id for r in scenario.rsus]))
        print(
            f"the reads a cached batch skips (HMGET of the session, HMGET of 4 RSUs), alone: {wall * 1e6:.0f} us "
            f"wall, {cpu * 1e6:.0f} us of this process's CPU per batch (median of 5 x 300)"
        )
        best, median, size = asyncio.run(_write_path(server.url("rt:")))
        print(
            f"a batch's write (compare-and-set pipeline) and 20-fix append ({size / 1e3:.0f} kB), alone: "
            f"{best * 1e6:.0f} us min, {median * 1e6:.0f} us median of this thread's CPU per batch (5 x 300)"
        )
    return 0


async def _skipped_reads(url: str, rsu_ids: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds of the token check's read and the RSU read of one batch, on a fresh store."""
    store = RedisStore(url, 60.0)
    now = time.time()
    record = SessionRecord("s", "car", "rsu_imu", {}, "h" * 64, os.urandom(20_000), now, now)
    await store.create(record, 10)
    await store.upsert_rsus([Rsu(rsu_id, 1.0, 2.0, 1.0, 0.1, 100.0) for rsu_id in rsu_ids])
    store.cache_rsus = False  # the RSU read as every batch made it before
    wanted = rsu_ids[:4]
    walls, cpus = [], []
    for _ in range(5):
        wall, cpu = time.perf_counter(), time.process_time()
        for _ in range(300):
            await store.get("s", with_response=False)
            await store.get_rsus(wanted)
        walls.append((time.perf_counter() - wall) / 300)
        cpus.append((time.process_time() - cpu) / 300)
    await store.close()
    return statistics.median(walls), statistics.median(cpus)


async def _write_path(url: str) -> tuple[float, float, int]:
    """Thread CPU seconds per batch (min and median of 5 x 300) of ``compare_and_set`` and a 20-fix
    ``append`` on a record the run wrote, and that record's size in bytes."""
    store = RedisStore(url, 60.0)
    log = store.fix_log(1000)
    (summary,) = (await store.list_sessions(limit=1))[:1]
    stored = await store.get(summary.session_id)
    assert stored is not None and stored.last_response is not None and stored.last_fix is not None
    record = dataclasses.replace(stored, session_id="write-path", vehicle_id="write-path", version=0)
    await store.create(dataclasses.replace(record, last_response=None), 10)
    fix = NewFix(record.session_id, record.vehicle_id, record.pipeline, 1.0, stored.last_fix.encode())
    fixes = [dataclasses.replace(fix, t=float(i)) for i in range(20)]
    version = 0

    async def batch() -> None:
        nonlocal version
        assert await store.compare_and_set(dataclasses.replace(record, updated_at=time.time()), version)
        version += 1
        await log.append(fixes)

    for _ in range(50):
        await batch()
    cpus = []
    for _ in range(5):
        cpu = time.thread_time()
        for _ in range(300):
            await batch()
        cpus.append((time.thread_time() - cpu) / 300)
    await store.close()
    await log.close()
    size = len(record.state) + len(stored.last_response) + len(stored.last_fix) * 20
    return min(cpus), statistics.median(cpus), size


def _drive(
    settings: Settings,
    rsus: dict[str, Any],
    bodies: list[dict[str, Any]],
    vehicles: int,
    counter: RoundTrips | None,
) -> tuple[list[float], float]:
    """Open the sessions and send every body to each in turn: the answer times and the CPU seconds."""
    times: list[float] = []
    with TestClient(create_app(settings)) as client:
        assert client.put("/v1/rsus", json=rsus, headers=ADMIN).status_code == 200
        sessions = []
        for vehicle in range(vehicles):
            created = client.post(
                "/v1/sessions", json={"vehicle_id": f"rt-{vehicle}", "pipeline": "rsu_imu"}, headers=ADMIN
            ).json()
            sessions.append((created["session_id"], {"Authorization": f"Bearer {created['token']}"}))
        if counter is not None:
            counter.counting = True
        cpu = time.process_time()
        for body in bodies:
            for session_id, token in sessions:
                started = time.perf_counter()
                response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token)
                times.append(time.perf_counter() - started)
                assert response.status_code == 200, response.text
        cpu = time.process_time() - cpu
        if counter is not None:
            counter.counting = False
    return times, cpu


if __name__ == "__main__":
    sys.exit(main())
