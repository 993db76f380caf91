"""Benchmark: what the Redis session store costs, against the in-process store, in one run.

Starts a ``redis-server`` on a free loopback port (append-only file on, ``appendfsync everysec``, the
recommended production setting; ``--persistence`` changes it) and, in turn, ``edgepos serve`` with

  * 1 worker on the in-process store (the baseline),
  * 1 worker on Redis,
  * 2 workers on Redis,

and puts the same loads on each from this process (the load generator shares the machine's cores
with the server; it reports its own lateness): a closed loop of 20 vehicles sending 20-epoch
batches (each vehicle sends its next batch as soon as the last is answered: the capacity), the same
with 2-epoch batches (the store's per-request cost weighs ten times more per epoch), and an open
loop of 40 vehicles at 20 Hz in 20-epoch batches (800 epochs/s offered: latency at a fixed load).
The in-process and Redis runs at 1 worker alternate for ``--rounds`` rounds so that drift of the
machine hits both alike; each figure is the median over rounds.

Halfway through each Redis run the benchmark reads the size of every live session's stored state
(``HSTRLEN`` of its ``state`` field): with the lag window at its default (``max_delay_s`` 1 s) a
session stores the filter states and measurements of the last second, and that size is what each
batch moves to and from Redis.

Printed: a table of epochs/s and p50/p99 latency per target and load, and the ratio of Redis to
in-process throughput at 1 worker for each closed-loop load (target: Redis costs at most 25 %,
i.e. ratio >= 0.75 with 20-epoch batches), with the machine's core count and load average.

    python bench/redis_store.py [--duration S] [--rounds N] [--persistence everysec|always|none] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import statistics
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edgepos.loadgen.loadtest import LoadConfig, LoadReport, run_load
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command

ADMIN_KEY = "bench-admin-key-" + os.urandom(8).hex()
RATIO_TARGET = 0.75
PERSISTENCE = {
    "none": ("--save", "", "--appendonly", "no"),
    "everysec": ("--save", "", "--appendonly", "yes", "--appendfsync", "everysec"),
    "always": ("--save", "", "--appendonly", "yes", "--appendfsync", "always"),
}


@dataclass(frozen=True)
class Load:
    name: str
    vehicles: int
    rate: float
    batch: int
    saturate: bool


LOADS = [
    Load("closed loop, 20 vehicles, 20-epoch batches", 20, 20.0, 20, True),
    Load("closed loop, 20 vehicles, 2-epoch batches", 20, 20.0, 2, True),
    Load("open loop, 40 vehicles x 20 Hz, 20-epoch batches", 40, 20.0, 20, False),
]
BASELINE, REDIS_1, REDIS_2 = "in-process store, 1 worker", "Redis store, 1 worker", "Redis store, 2 workers"


def measure(url: str, load: Load, duration: float) -> LoadReport:
    config = LoadConfig(
        url=url,
        vehicles=load.vehicles,
        rate=load.rate,
        batch=load.batch,
        duration=duration,
        admin_key=ADMIN_KEY,
        saturate=load.saturate,
        timeout=60.0,
    )
    return asyncio.run(run_load(config))


def sample_state_sizes(redis: RedisServer, prefix: str, delay: float, sizes: list[int]) -> threading.Thread:
    """Start a thread that, after ``delay`` seconds, appends the stored state size (bytes) of every live
    session under ``prefix`` to ``sizes``."""
    import redis as redis_py  # the store's own client library

    def sample() -> None:
        time.sleep(delay)
        client = redis_py.Redis(host="127.0.0.1", port=redis.port)
        try:
            keys = list(client.scan_iter(match=f"{prefix}session:*", count=1000))
            pipe = client.pipeline(transaction=False)
            for key in keys:
                pipe.hstrlen(key, "state")
            sizes.extend(int(n) for n in pipe.execute() if n)
        finally:
            client.close()

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    return thread


def summary(reports: list[LoadReport]) -> dict[str, Any]:
    """Median over rounds of each figure, plus the errors summed."""

    def median(values: list[float | None]) -> float | None:
        present = [v for v in values if v is not None]
        return statistics.median(present) if present else None

    return {
        "epochs_per_s": median([r.epochs_per_s for r in reports]),
        "p50_ms": median([r.latency(50) for r in reports]),
        "p99_ms": median([r.latency(99) for r in reports]),
        "errors": sum(r.errors for r in reports),
        "rounds": [r.to_json() for r in reports],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=12.0, help="seconds per load run (default 12)")
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds at 1 worker (default 2)")
    parser.add_argument("--persistence", choices=sorted(PERSISTENCE), default="everysec")
    parser.add_argument("--json", type=Path, default=None, help="also write every figure as JSON")
    args = parser.parse_args()
    binary = redis_binary()
    if binary is None:
        print("redis-server is not installed (apt-get install -y redis-server)", file=sys.stderr)
        return 2
    began = time.perf_counter()
    load_before = os.getloadavg()
    print(
        f"edgepos Redis store benchmark: {os.cpu_count()} cores, {platform.python_implementation()} "
        f"{platform.python_version()}, load average {load_before[0]:.2f} at start, Redis persistence "
        f"{args.persistence}, {args.duration:g} s per run, {args.rounds} round(s)",
        flush=True,
    )
    results: dict[tuple[str, str], list[LoadReport]] = {}
    state_sizes: list[int] = []
    with tempfile.TemporaryDirectory(prefix="edgepos-bench-redis-") as tmp:
        workdir = Path(tmp)
        base_env = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
            EDGEPOS_LOG_LEVEL="warning",
            # Capacity, not policy: a closed loop of 2-epoch batches on the in-process store asks more than
            # the default 50 requests/s per session, and 429s would be counted as errors.
            EDGEPOS_RATE_LIMIT_PER_S="0",
        )
        with RedisServer(binary, workdir / "redis", *PERSISTENCE[args.persistence]) as redis:
            redis_env = {**base_env, "EDGEPOS_STORE": redis.url("bench:")}
            plan = [(BASELINE, 1, base_env), (REDIS_1, 1, redis_env)] * args.rounds + [
                (REDIS_2, 2, redis_env)
            ]
            for target, workers, environment in plan:
                log_path = workdir / f"{target.replace(' ', '-').replace(',', '')}.log"
                with running(serve_command(workers), environment, log_path) as url:
                    for load in LOADS:
                        sampler = (
                            sample_state_sizes(redis, "bench:", args.duration / 2, state_sizes)
                            if environment is redis_env
                            else None
                        )
                        report = measure(url, load, args.duration)
                        if sampler is not None:
                            sampler.join()
                        results.setdefault((target, load.name), []).append(report)
                        print(
                            f"  {target}: {load.name}: {report.epochs_per_s:.0f} epochs/s, "
                            f"p50 {report.latency(50) or float('nan'):.1f} ms, "
                            f"p99 {report.latency(99) or float('nan'):.1f} ms, {report.errors} errors",
                            flush=True,
                        )

    figures = {f"{target} | {load}": summary(reports) for (target, load), reports in results.items()}
    print()
    header = f"{'target':<28} {'load':<50} {'epochs/s':>9} {'p50 ms':>8} {'p99 ms':>8} {'errors':>6}"
    print(header)
    print("-" * len(header))
    for load in LOADS:
        for target in (BASELINE, REDIS_1, REDIS_2):
            row = figures[f"{target} | {load.name}"]
            print(
                f"{target:<28} {load.name:<50} {row['epochs_per_s']:>9.0f} {row['p50_ms']:>8.1f} "
                f"{row['p99_ms']:>8.1f} {row['errors']:>6}"
            )
    print()
    verdicts: dict[str, float] = {}
    for load in LOADS:
        if not load.saturate:
            continue
        rounds = zip(results[(BASELINE, load.name)], results[(REDIS_1, load.name)], strict=True)
        ratios = [redis.epochs_per_s / memory.epochs_per_s for memory, redis in rounds]
        ratio = statistics.median(ratios)
        verdicts[load.name] = ratio
        scaling = (
            figures[f"{REDIS_2} | {load.name}"]["epochs_per_s"]
            / figures[f"{REDIS_1} | {load.name}"]["epochs_per_s"]
        )
        target_note = (
            f" (target >= {RATIO_TARGET}: {'PASS' if ratio >= RATIO_TARGET else 'FAIL'})"
            if load.batch == 20
            else ""
        )
        print(
            f"{load.name}: Redis / in-process at 1 worker = {ratio:.2f} "
            f"(rounds: {', '.join(f'{r:.2f}' for r in ratios)}){target_note}; "
            f"Redis 2 workers / 1 worker = {scaling:.2f}"
        )
    if state_sizes:
        print(
            f"session state stored in Redis (lag window at its default, max_delay_s 1 s), sampled mid-run: "
            f"{len(state_sizes)} samples, median {statistics.median(state_sizes):.0f} B, "
            f"max {max(state_sizes)} B"
        )
    print(
        f"cores: {os.cpu_count()}; load average {load_before[0]:.2f} before, {os.getloadavg()[0]:.2f} after; "
        f"whole benchmark {time.perf_counter() - began:.0f} s"
    )
    if args.json is not None:
        document = {
            "cores": os.cpu_count(),
            "persistence": args.persistence,
            "duration_s": args.duration,
            "load_average_start": load_before[0],
            "figures": figures,
            "ratios_redis_over_memory_1_worker": verdicts,
            "state_bytes": {
                "samples": len(state_sizes),
                "median": statistics.median(state_sizes) if state_sizes else None,
                "max": max(state_sizes, default=None),
            },
        }
        args.json.write_text(json.dumps(document, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
