"""Benchmark: what waiting for a replica costs (EDGEPOS_REDIS_WAIT_REPLICAS=1 against 0), in one run.

Starts on loopback a Redis primary (append-only file, ``appendfsync everysec``) with one replica, and
in turn ``edgepos serve`` (1 worker) on it with ``EDGEPOS_REDIS_WAIT_REPLICAS`` 0 and 1, and puts the
same closed loops on each from this process with ``edgepos loadtest``'s generator: 20 vehicles
sending 20-epoch batches, then 2-epoch batches (the per-request cost weighs ten times more per epoch),
each as soon as the previous one is answered. The two settings alternate for ``--rounds`` rounds so
that drift of the machine hits both alike; printed are epochs/s and p50/p99 per run, and the ratio of
WAIT 1 to WAIT 0 throughput per load (medians over rounds). Every session is verified at the end.

    python bench/redis_wait.py [--duration S] [--rounds N]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from edgepos.loadgen.loadtest import LoadConfig, run_load
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command

ADMIN_KEY = "wait-admin-key-" + os.urandom(8).hex()
LOADS = ((20, 20), (20, 2))  # (vehicles, epochs per batch)


def link_up(primary: RedisServer, replica: RedisServer) -> None:
    deadline = time.monotonic() + 30.0
    while b"master_link_status:up" not in replica.command("INFO", "replication") or (
        b"connected_slaves:1" not in primary.command("INFO", "replication")
    ):
        if time.monotonic() > deadline:
            raise RuntimeError("the replica did not connect to its primary")
        time.sleep(0.05)


def store_level(primary: RedisServer, writes: int) -> None:
    """One client's get + compare-and-set of a session, WAIT 0 and WAIT 1 interleaved write by write:
    the added latency of a batch without the service's noise around it."""
    import dataclasses

    from edgepos.store.base import SessionRecord
    from edgepos.store.redis import RedisStore

    async def run() -> dict[int, list[float]]:
        stores = {
            wait: RedisStore(primary.url(f"store{wait}:"), 3600.0, wait_replicas=wait) for wait in (0, 1)
        }
        now = time.time()
        for store in stores.values():
            record = SessionRecord("s", "v", "rsu_imu", {}, "ab" * 32, b"x" * 15_000, now, now)
            await store.create(record, max_sessions=10)
        timings: dict[int, list[float]] = {0: [], 1: []}
        for _ in range(writes):
            for wait, store in stores.items():
                started = time.perf_counter()
                current = await store.get("s")
                assert current is not None
                await store.compare_and_set(
                    dataclasses.replace(current, last_seq=current.last_seq + 1), current.version
                )
                timings[wait].append((time.perf_counter() - started) * 1e6)
        for store in stores.values():
            await store.close()
        return timings

    timings = asyncio.run(run())
    zero, one = (statistics.median(timings[w]) for w in (0, 1))
    print(
        f"store level, one client, get + compare-and-set of a 15 kB session state, {writes} writes each, interleaved: "
        f"WAIT 0 {zero:.0f} us, WAIT 1 {one:.0f} us median (+{one - zero:.0f} us)"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=8.0, help="seconds per load run (default 8)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument(
        "--writes", type=int, default=2000, help="store-level writes per setting (default 2000)"
    )
    args = parser.parse_args()
    binary = redis_binary()
    if binary is None:
        print("redis-server is not installed (make redis-server)", file=sys.stderr)
        return 2
    load_before = os.getloadavg()[0]
    results: dict[tuple[int, int, int], list[tuple[float, float | None, float | None]]] = {}
    with tempfile.TemporaryDirectory(prefix="edgepos-wait-") as scratch:
        directory = Path(scratch)
        primary = RedisServer(
            binary, directory / "primary", "--appendonly", "yes", "--appendfsync", "everysec", "--save", ""
        )
        primary.start()
        replica = RedisServer(
            binary, directory / "replica", "--save", "", "--replicaof", "127.0.0.1", str(primary.port)
        )
        try:
            replica.start()
            link_up(primary, replica)
            store_level(primary, args.writes)
            for round_number in range(args.rounds):
                for wait in (0, 1):
                    environment = clean_environment(
                        EDGEPOS_STORE=primary.url(f"wait{wait}r{round_number}:"),
                        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
                        EDGEPOS_DEMO_RSUS="true",
                        EDGEPOS_RATE_LIMIT_PER_S="0",
                        EDGEPOS_REDIS_WAIT_REPLICAS=str(wait),
                    )
                    log = directory / f"serve-{wait}-{round_number}.log"
                    with running(serve_command(1), environment, log, ready_timeout_s=300) as url:
                        for vehicles, batch in LOADS:
                            config = LoadConfig(
                                url=url,
                                vehicles=vehicles,
                                rate=20.0,
                                batch=batch,
                                duration=args.duration,
                                admin_key=ADMIN_KEY,
                                saturate=True,
                                verify=True,
                            )
                            report = asyncio.run(run_load(config)).to_json()
                            verify = report["verify"]
                            if (
                                report["errors"]
                                or verify["lost"]
                                or verify["mismatches"]
                                or verify["unreadable"]
                            ):
                                print(
                                    f"WAIT {wait}: errors or a failed verify: {report['errors_by_code']} {verify}"
                                )
                            row = (
                                report["epochs_per_s"],
                                report["latency_ms"]["p50"],
                                report["latency_ms"]["p99"],
                            )
                            results.setdefault((wait, vehicles, batch), []).append(row)
                            print(
                                f"round {round_number + 1} WAIT {wait}: {vehicles} vehicles x {batch}-epoch batches: "
                                f"{row[0]:.0f} epochs/s, p50 {row[1]:.1f} ms, p99 {row[2]:.1f} ms, "
                                f"{report['errors']} errors, {verify['found']} of {verify['acknowledged_batches']} "
                                "acknowledged batches found"
                            )
        finally:
            replica.stop()
            primary.stop()
    print()
    for vehicles, batch in LOADS:
        zero = [row[0] for row in results[(0, vehicles, batch)]]
        one = [row[0] for row in results[(1, vehicles, batch)]]
        ratios = [b / a for a, b in zip(zero, one, strict=True)]
        print(
            f"closed loop, {vehicles} vehicles, {batch}-epoch batches: WAIT 1 / WAIT 0 = {statistics.median(ratios):.2f} "
            f"(rounds: {', '.join(f'{r:.2f}' for r in ratios)}); epochs/s {statistics.median(zero):.0f} -> "
            f"{statistics.median(one):.0f}; p99 {statistics.median(r[2] for r in results[(0, vehicles, batch)]):.1f} -> "
            f"{statistics.median(r[2] for r in results[(1, vehicles, batch)]):.1f} ms"
        )
    print(f"cores: {os.cpu_count()}; load average {load_before:.2f} before, {os.getloadavg()[0]:.2f} after")
    return 0


if __name__ == "__main__":
    sys.exit(main())
