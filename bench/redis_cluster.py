"""Benchmark: two workers on a local Redis Cluster against two workers on one Redis, same load.

For each round and each store, in alternation: start the store on loopback (one ``redis-server``, or
three primaries and three replicas joined by ``redis-cli --cluster create``; append-only file on,
``appendfsync everysec``, on every node), ``edgepos serve --workers 2`` on it, and ``edgepos
loadtest`` as its own process, closed loop (each vehicle sends its next batch once the last is
answered) with ``--verify``. Prints per round the epochs/s, p99, errors and lost batches of both, the
ratio cluster / one Redis, the sessions per primary half way through the cluster run, and what the
capacity model in docs/redis.md needs: Redis commands per batch and Redis CPU per batch (from
``INFO commandstats`` and ``INFO cpu`` before and after, summed over primaries) and the service's CPU
per batch (its processes' user and system time from /proc).

    python bench/redis_cluster.py [--vehicles 64] [--batch 20] [--duration 20] [--rounds 2] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import redis
from edgepos.loadgen.localredis import RedisClusterProcesses, RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command, service_cpu_s

ADMIN_KEY = "cluster-bench-admin-" + os.urandom(8).hex()
PREFIX = "bench:"
PERSISTENCE = ("--save", "", "--appendonly", "yes", "--appendfsync", "everysec")


@contextmanager
def _store(kind: str, binary: str, workdir: Path) -> Iterator[tuple[str, list[int]]]:
    """(store URL, the primaries' ports) of a fresh single Redis or cluster."""
    if kind == "redis":
        with RedisServer(binary, workdir / "redis", *PERSISTENCE) as server:
            yield server.url(PREFIX), [server.port]
    else:
        with RedisClusterProcesses(binary, workdir / "cluster", *PERSISTENCE) as cluster:
            yield cluster.url(PREFIX), [node.port for node in cluster.primaries()]


def _stats(ports: list[int]) -> dict[str, float]:
    """Commands and CPU seconds summed over ``ports`` (their INFO)."""
    calls = cpu = 0.0
    for port in ports:
        client = redis.Redis(host="127.0.0.1", port=port)
        for name, entry in client.info("commandstats").items():
            if name not in ("cmdstat_info", "cmdstat_cluster", "cmdstat_ping", "cmdstat_scan"):
                calls += float(entry["calls"])
        info = client.info("cpu")
        cpu += float(info["used_cpu_sys"]) + float(info["used_cpu_user"])
        client.close()
    return {"calls": calls, "cpu_s": cpu}


def _sessions_by_primary(ports: list[int]) -> list[int]:
    counts = []
    for port in ports:
        client = redis.Redis(host="127.0.0.1", port=port)
        counts.append(sum(1 for _ in client.scan_iter(match=f"{PREFIX}*session:*", count=1000)))
        client.close()
    return counts


def _run(kind: str, binary: str, args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix=f"edgepos-{kind}-") as tmp:
        workdir = Path(tmp)
        environment = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
            EDGEPOS_LOG_LEVEL="warning",
            EDGEPOS_MAX_SESSIONS=str(max(10_000, 2 * args.vehicles)),
        )
        with _store(kind, binary, workdir) as (store_url, ports):
            environment["EDGEPOS_STORE"] = store_url
            with running(serve_command(2), environment, workdir / "server.log") as url:
                report_path = workdir / "report.json"
                command = [
                    sys.executable, "-m", "edgepos.cli", "loadtest", "--url", url,
                    "--vehicles", str(args.vehicles), "--rate", "20", "--batch", str(args.batch),
                    "--duration", str(args.duration), "--admin-key", ADMIN_KEY, "--timeout", "30",
                    "--saturate", "--verify", "--json", str(report_path),
                ]  # fmt: skip
                spread: dict[str, list[int]] = {}

                def sample() -> None:
                    time.sleep(args.duration / 2)
                    spread["sessions"] = _sessions_by_primary(ports)

                before, service_before = _stats(ports), service_cpu_s(url)
                sampler = threading.Thread(target=sample, daemon=True)
                sampler.start()
                # its exit status says what the report says (lost batches): the report is read below
                subprocess.run(
                    command,
                    env={**os.environ, "EDGEPOS_ADMIN_KEY": ADMIN_KEY},
                    stdout=subprocess.DEVNULL,
                    check=False,
                )
                sampler.join()
                after, service_cpu = _stats(ports), service_cpu_s(url) - service_before
                report = json.loads(report_path.read_text())
    batches = max(1, report["requests"])
    return {
        "epochs_per_s": report["epochs_per_s"],
        "p99_ms": report["latency_ms"]["p99"],
        "errors": report["errors"],
        "lost": report["verify"]["lost"],
        "batches": report["requests"],
        "redis_calls_per_batch": (after["calls"] - before["calls"]) / batches,
        "redis_cpu_us_per_batch": (after["cpu_s"] - before["cpu_s"]) / batches * 1e6,
        "service_cpu_us_per_batch": service_cpu / batches * 1e6,
        "sessions_by_primary": spread.get("sessions"),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=64)
    parser.add_argument("--batch", type=int, default=20, help="epochs per batch (default 20)")
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    binary = redis_binary()
    if binary is None:
        print("redis-server is not installed (apt-get install -y redis-server)", file=sys.stderr)
        return 2
    print(
        f"Redis Cluster benchmark: {args.vehicles} vehicles, closed loop, {args.batch}-epoch batches, "
        f"{args.duration:g} s per run, 2 workers, AOF everysec; {os.cpu_count()} cores, load average "
        f"{os.getloadavg()[0]:.2f}",
        flush=True,
    )
    rounds = []
    for index in range(args.rounds):
        order = ("redis", "cluster") if index % 2 == 0 else ("cluster", "redis")
        result = {kind: _run(kind, binary, args) for kind in order}
        ratio = result["cluster"]["epochs_per_s"] / result["redis"]["epochs_per_s"]
        rounds.append({**result, "ratio": ratio, "load_average": os.getloadavg()[0]})
        for kind in ("redis", "cluster"):
            r = result[kind]
            print(
                f"round {index + 1} {kind:8s} {r['epochs_per_s']:8.0f} epochs/s  p99 {r['p99_ms']:.0f} ms  "
                f"errors {r['errors']}  lost {r['lost']}  per batch: {r['redis_calls_per_batch']:.2f} Redis "
                f"commands (a script's own calls included), {r['redis_cpu_us_per_batch']:.0f} us Redis CPU, "
                f"{r['service_cpu_us_per_batch']:.0f} us service CPU"
                + (f"  sessions per primary {r['sessions_by_primary']}" if kind == "cluster" else ""),
                flush=True,
            )
        print(
            f"round {index + 1} cluster / one Redis = {ratio:.2f} (load average {os.getloadavg()[0]:.2f})",
            flush=True,
        )
    if args.json is not None:
        args.json.write_text(json.dumps(rounds, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
