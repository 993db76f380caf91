"""Benchmark: the server's CPU per epoch, A/B between source trees (e.g. a commit in a git worktree).

For each round and each tree, in alternation: ``edgepos serve`` (one worker, the demo RSU map) from that
tree, and ``edgepos loadtest`` (from this tree) in closed loop, 16 vehicles, for ``--duration`` s. Prints
the epochs/s and the server's own CPU time (user + system, from /proc) per epoch: on a shared machine CPU
time is disturbed far less than wall-clock throughput. The store is the in-process one, or with ``--store
redis`` a ``redis-server`` started afresh for each run (append-only file, ``appendfsync everysec``, as
bench/wrk_load.py's), whose own CPU per epoch is printed too: it shares the machine's cores with the worker.

    git worktree add /tmp/base 2a9c7e1
    python bench/service_cpu.py --tree base=/tmp/base --tree now=. --batch 1 --rounds 3 [--store redis] \
        [--log-level info]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, service_cpu_s

ADMIN_KEY = "cpu-bench-admin-" + os.urandom(8).hex()
HERE = Path(__file__).resolve().parents[1]


def _process_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of one process so far, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _one(tree: Path, args: argparse.Namespace) -> tuple[float, float, float]:
    """(epochs/s, server CPU µs per epoch, redis-server CPU µs per epoch) of one closed-loop run against a
    server from ``tree``."""
    with tempfile.TemporaryDirectory(prefix="edgepos-cpu-") as tmp, contextlib.ExitStack() as stack:
        environment = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=f"{tmp}/admin.key",
            EDGEPOS_LOG_LEVEL=args.log_level,
            EDGEPOS_DEMO_RSUS="true",
        )
        redis_pid = None
        if args.store == "redis":
            binary = redis_binary()
            if binary is None:
                raise SystemExit("redis-server is not installed: `make redis-server` installs it")
            redis = stack.enter_context(
                RedisServer(binary, Path(tmp) / "redis", "--appendonly", "yes", "--appendfsync", "everysec")
            )
            assert redis.process is not None
            redis_pid = redis.process.pid
            environment["EDGEPOS_STORE"] = redis.url(prefix="cpu")
        environment["PYTHONPATH"] = f"{tree}/service:{tree}/client"
        command = [sys.executable, "-m", "edgepos.cli", "serve", "--host", "127.0.0.1", "--port", "{port}"]
        with running(command, environment, Path(tmp) / "server.log", ready_timeout_s=300) as url:
            before = service_cpu_s(url)
            redis_before = 0.0 if redis_pid is None else _process_cpu_s(redis_pid)
            report_path = Path(tmp) / "report.json"
            load = [
                sys.executable, "-m", "edgepos.cli", "loadtest", "--url", url, "--vehicles", "16",
                "--rate", "20", "--batch", str(args.batch), "--duration", str(args.duration), "--saturate",
                "--admin-key", ADMIN_KEY, "--json", str(report_path),
            ]  # fmt: skip
            own = {**os.environ, "PYTHONPATH": f"{HERE}/service:{HERE}/client"}
            subprocess.run(load, env=own, stdout=subprocess.DEVNULL, check=True)
            cpu_s = service_cpu_s(url) - before
            redis_s = 0.0 if redis_pid is None else _process_cpu_s(redis_pid) - redis_before
            report = json.loads(report_path.read_text())
    epochs = max(1, report["epochs"])
    return report["epochs_per_s"], cpu_s / epochs * 1e6, redis_s / epochs * 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--tree", action="append", required=True, metavar="NAME=PATH", help="a source tree (twice)"
    )
    parser.add_argument("--batch", type=int, default=20, help="epochs per batch (default 20)")
    parser.add_argument("--duration", type=float, default=15.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--store", choices=("memory", "redis"), default="memory")
    parser.add_argument(
        "--log-level",
        default="warning",
        help="the servers' EDGEPOS_LOG_LEVEL: warning (default) writes no access line, info (the service's "
        "default) one a request, as in production",
    )
    args = parser.parse_args()
    trees = {name: Path(path).resolve() for name, _, path in (item.partition("=") for item in args.tree)}
    print(
        f"server CPU per epoch, {args.batch}-epoch batches, closed loop of 16 vehicles, {args.duration:g} s per "
        f"run, 1 worker, {args.store} store, log level {args.log_level}; load average {os.getloadavg()[0]:.2f}",
        flush=True,
    )
    results: dict[str, list[tuple[float, float, float]]] = {name: [] for name in trees}
    for index in range(args.rounds):
        order = list(trees) if index % 2 == 0 else list(reversed(trees))
        for name in order:
            epochs_per_s, cpu_us, redis_us = _one(trees[name], args)
            results[name].append((epochs_per_s, cpu_us, redis_us))
            redis_text = f"  {redis_us:6.1f} us redis-server CPU" if args.store == "redis" else ""
            print(
                f"round {index + 1} {name:10s} {epochs_per_s:7.0f} epochs/s  {cpu_us:7.1f} us server CPU per epoch"
                f"{redis_text}  load average {os.getloadavg()[0]:.2f}",
                flush=True,
            )
    for name, rows in results.items():
        print(
            f"{name:10s} medians: {statistics.median(r[0] for r in rows):.0f} epochs/s, "
            f"{statistics.median(r[1] for r in rows):.1f} us server CPU per epoch (minimum "
            f"{min(r[1] for r in rows):.1f})"
            + (
                f", {statistics.median(r[2] for r in rows):.1f} us redis-server CPU"
                if args.store == "redis"
                else ""
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
