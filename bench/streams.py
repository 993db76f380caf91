"""Benchmark: the fleet load with and without fix stream consumers attached.

Starts ``redis-server`` on a free loopback port (no persistence) and ``edgepos serve --workers 2`` on it
(``--store memory`` for one worker on the in-process store instead), then runs, in interleaved rounds,
the same open-loop fleet load (the load test's vehicles x rate in batches, as bench/fleet_redis.py)
twice: with no consumer, and with ``--consumers`` admin consumers of ``GET /v1/stream/fixes`` attached
for the whole run, in a process of their own (so their parsing does not slow the load generator's
loop). Each consumer counts the fix events it received. Printed per run: epochs/s, p50/p99 latency,
errors, the service's CPU seconds (its processes, from /proc) and the events each consumer received
against the fixes applied; then the median ratios with consumers to without of epochs/s, p99 and
service CPU per fix, the core count and the load average. Loopback only; every
run is bounded by ``--duration``.

    python bench/streams.py [--vehicles N] [--rate HZ] [--batch B] [--duration S] [--rounds R]
        [--consumers C] [--store redis|memory] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
from edgepos.loadgen.loadtest import LoadConfig, LoadReport, run_load
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command, service_cpu_s

ADMIN_KEY = "streams-admin-key-" + os.urandom(8).hex()
DRAIN_S = 1.0
"""After a run, how long the consumers may take to receive what the stream still carries."""


# -- the consumers' process ----------------------------------------------------------------------------
async def _consume(
    url: str, key: str, counts: list[int], ends: list[int], index: int, ready: asyncio.Event
) -> None:
    """Count the fix events of one stream from its raw bytes (cheaper than parsing lines: the consumers share
    the machine's cores with the server and the load generator)."""
    headers = {"Authorization": f"Bearer {key}", "Accept": "text/event-stream"}
    timeout = httpx.Timeout(10.0, read=None)
    fix, end = b"event: fix\n", b"event: end\n"
    async with (
        httpx.AsyncClient(timeout=timeout) as client,
        client.stream("GET", f"{url}/v1/stream/fixes", headers=headers) as response,
    ):
        response.raise_for_status()
        ready.set()
        tail = b""
        async for raw in response.aiter_raw():
            data = tail + raw
            counts[index] += data.count(fix)
            ends[index] += data.count(end)
            # the bytes a marker split across two reads could start in (a full marker is never counted twice)
            tail = data[-(len(fix) - 1) :]


async def _consumers(url: str, key: str, count: int) -> dict[str, Any]:
    counts, ends = [0] * count, [0] * count
    readies = [asyncio.Event() for _ in range(count)]
    tasks = [asyncio.create_task(_consume(url, key, counts, ends, i, readies[i])) for i in range(count)]
    await asyncio.gather(*(ready.wait() for ready in readies))
    print("ready", flush=True)
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)  # until the bench closes stdin
    for task in tasks:
        task.cancel()
    failures = [
        repr(r)
        for r in await asyncio.gather(*tasks, return_exceptions=True)
        if not isinstance(r, asyncio.CancelledError)
    ]
    return {"events": counts, "ends": ends, "failures": failures, "cpu_s": time.process_time()}


def consumer_main(url: str, key: str, count: int) -> int:
    print(json.dumps(asyncio.run(_consumers(url, key, count))), flush=True)
    return 0


# -- the bench -----------------------------------------------------------------------------------------
@contextlib.contextmanager
def attached(url: str, count: int):
    """``count`` consumers in a process of their own, connected before the block and counted after it."""
    result: dict[str, Any] = {}
    if count == 0:
        yield result
        return
    process = subprocess.Popen(
        [sys.executable, __file__, "--consume", url, "--consumers", str(count)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env={**os.environ, "EDGEPOS_ADMIN_KEY": ADMIN_KEY},
        text=True,
    )
    assert process.stdout is not None and process.stdin is not None
    line = process.stdout.readline()
    if line.strip() != "ready":
        process.kill()
        raise RuntimeError(f"the consumers did not connect: {line!r}")
    try:
        yield result
        time.sleep(DRAIN_S)
    finally:
        process.stdin.close()
        output = process.stdout.read()
        process.wait(timeout=30)
        result.update(json.loads(output.strip().splitlines()[-1]))


def _run(url: str, args: argparse.Namespace, consumers: int) -> tuple[LoadReport, dict[str, Any], float]:
    config = LoadConfig(
        url=url,
        vehicles=args.vehicles,
        rate=args.rate,
        batch=args.batch,
        duration=args.duration,
        admin_key=ADMIN_KEY,
        timeout=30.0,
    )
    with attached(url, consumers) as counted:
        cpu_before = service_cpu_s(url)
        report = asyncio.run(run_load(config))
        cpu_s = service_cpu_s(url) - cpu_before
    return report, counted, cpu_s


def _line(label: str, report: LoadReport, counted: dict[str, Any], cpu_s: float) -> str:
    p50, p99 = report.latency(50), report.latency(99)
    per_1000 = 1000.0 * cpu_s / report.recorder.epochs if report.recorder.epochs else float("nan")
    text = (
        f"  {label}: {report.epochs_per_s:.0f} epochs/s, p50 {p50 or float('nan'):.1f} ms, "
        f"p99 {p99 or float('nan'):.1f} ms, {report.errors} errors, {report.recorder.epochs} fixes applied, "
        f"service CPU {cpu_s:.1f} s ({per_1000:.2f} s per 1000 fixes)"
    )
    if counted:
        events = counted["events"]
        text += (
            f"; events per consumer min {min(events)} / median {statistics.median(events):.0f} / max {max(events)}, "
            f"{sum(counted['ends'])} dropped; the consumers' process used {counted['cpu_s']:.1f} s CPU"
        )
    return text


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=200)
    parser.add_argument("--rate", type=float, default=10.0, help="epochs per second per vehicle (default 10)")
    parser.add_argument("--batch", type=int, default=5, help="epochs per batch (default 5: 2 batches/s)")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per run (default 20)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of (no consumer, consumers) runs")
    parser.add_argument("--consumers", type=int, default=10)
    parser.add_argument("--store", choices=("redis", "memory"), default="redis")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--consume", default=None, help=argparse.SUPPRESS)  # the consumers' own process
    args = parser.parse_args()
    if args.consume is not None:
        return consumer_main(args.consume, os.environ["EDGEPOS_ADMIN_KEY"], args.consumers)
    if not 0 < args.duration <= 600 or args.rounds < 1 or not 0 < args.consumers <= 100:
        parser.error("--duration in (0, 600], --rounds >= 1, --consumers in [1, 100]")
    load_before = os.getloadavg()
    began = time.perf_counter()
    workers = 2 if args.store == "redis" else 1
    print(
        f"stream benchmark {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}: {args.vehicles} vehicles x "
        f"{args.rate:g} Hz in {args.batch}-epoch batches, {args.duration:g} s per run, {args.rounds} round(s) of "
        f"0 and {args.consumers} consumers; {workers} worker(s) on {args.store}; {os.cpu_count()} cores, "
        f"load average {load_before[0]:.2f}",
        flush=True,
    )
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="edgepos-streams-") as tmp, contextlib.ExitStack() as stack:
        workdir = Path(tmp)
        environment = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
            EDGEPOS_LOG_LEVEL="warning",
            EDGEPOS_RATE_LIMIT_PER_S="0",
            EDGEPOS_MAX_SESSIONS=str(max(10_000, 2 * args.vehicles)),
        )
        if args.store == "redis":
            binary = redis_binary()
            if binary is None:
                print("redis-server is not installed (apt-get install -y redis-server)", file=sys.stderr)
                return 2
            redis = stack.enter_context(
                RedisServer(binary, workdir / "redis", "--save", "", "--appendonly", "no")
            )
            environment["EDGEPOS_STORE"] = redis.url("streams:")
        url = stack.enter_context(
            running(serve_command(workers), environment, workdir / "server.log", ready_timeout_s=300.0)
        )
        for number in range(1, args.rounds + 1):
            for consumers in (0, args.consumers):
                report, counted, cpu_s = _run(url, args, consumers)
                label = f"round {number}, {consumers} consumers"
                print(_line(label, report, counted, cpu_s), flush=True)
                runs.append(
                    {
                        "round": number,
                        "consumers": consumers,
                        **report.to_json(),
                        "stream": counted,
                        "service_cpu_s": cpu_s,
                    }
                )
    without = [r for r in runs if r["consumers"] == 0]
    with_ = [r for r in runs if r["consumers"] > 0]
    epochs_ratio = statistics.median(w["epochs_per_s"] / o["epochs_per_s"] for w, o in zip(with_, without))
    p99_ratio = statistics.median(
        w["latency_ms"]["p99"] / o["latency_ms"]["p99"] for w, o in zip(with_, without)
    )
    received = [
        statistics.median(r["stream"]["events"]) / r["epochs"] if r["epochs"] else float("nan") for r in with_
    ]
    cpu_ratio = statistics.median(
        (w["service_cpu_s"] / w["epochs"]) / (o["service_cpu_s"] / o["epochs"])
        for w, o in zip(with_, without)
    )
    print(
        f"with {args.consumers} consumers / without, median over rounds: epochs/s x{epochs_ratio:.3f}, "
        f"p99 x{p99_ratio:.2f}, service CPU per fix x{cpu_ratio:.2f}; median events per consumer / fixes applied: "
        f"{', '.join(f'{value:.3f}' for value in received)}"
    )
    print(
        f"load average {load_before[0]:.2f} before, {os.getloadavg()[0]:.2f} after; {time.perf_counter() - began:.0f} s"
    )
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {"runs": runs, "epochs_ratio": epochs_ratio, "p99_ratio": p99_ratio, "cpu_ratio": cpu_ratio},
                indent=2,
            )
            + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
