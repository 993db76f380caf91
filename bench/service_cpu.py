"""Benchmark: the server's CPU per epoch, A/B between source trees (e.g. a commit in a git worktree).

For each round and each tree, in alternation: ``edgepos serve`` (one worker, in-process store, the
demo RSU map) from that tree, and ``edgepos loadtest`` (from this tree) in closed loop, 16 vehicles,
for ``--duration`` s. Prints the epochs/s and the server's own CPU time (user + system, from /proc)
per epoch: on a shared machine CPU time is disturbed far less than wall-clock throughput.

    git worktree add /tmp/base 2a9c7e1
    python bench/service_cpu.py --tree base=/tmp/base --tree now=. --batch 1 --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from edgepos.loadgen.localserver import clean_environment, running, service_cpu_s

ADMIN_KEY = "cpu-bench-admin-" + os.urandom(8).hex()
HERE = Path(__file__).resolve().parents[1]


def _one(tree: Path, args: argparse.Namespace) -> tuple[float, float]:
    """(epochs/s, server CPU µs per epoch) of one closed-loop run against a server from ``tree``."""
    with tempfile.TemporaryDirectory(prefix="edgepos-cpu-") as tmp:
        environment = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=f"{tmp}/admin.key",
            EDGEPOS_LOG_LEVEL="warning",
            EDGEPOS_DEMO_RSUS="true",
        )
        environment["PYTHONPATH"] = f"{tree}/service:{tree}/client"
        command = [sys.executable, "-m", "edgepos.cli", "serve", "--host", "127.0.0.1", "--port", "{port}"]
        with running(command, environment, Path(tmp) / "server.log", ready_timeout_s=300) as url:
            before = service_cpu_s(url)
            report_path = Path(tmp) / "report.json"
            load = [
                sys.executable, "-m", "edgepos.cli", "loadtest", "--url", url, "--vehicles", "16",
                "--rate", "20", "--batch", str(args.batch), "--duration", str(args.duration), "--saturate",
                "--admin-key", ADMIN_KEY, "--json", str(report_path),
            ]  # fmt: skip
            own = {**os.environ, "PYTHONPATH": f"{HERE}/service:{HERE}/client"}
            subprocess.run(load, env=own, stdout=subprocess.DEVNULL, check=True)
            cpu_s = service_cpu_s(url) - before
            report = json.loads(report_path.read_text())
    return report["epochs_per_s"], cpu_s / max(1, report["epochs"]) * 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--tree", action="append", required=True, metavar="NAME=PATH", help="a source tree (twice)"
    )
    parser.add_argument("--batch", type=int, default=20, help="epochs per batch (default 20)")
    parser.add_argument("--duration", type=float, default=15.0)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    trees = {name: Path(path).resolve() for name, _, path in (item.partition("=") for item in args.tree)}
    print(
        f"server CPU per epoch, {args.batch}-epoch batches, closed loop of 16 vehicles, {args.duration:g} s per "
        f"run, 1 worker; load average {os.getloadavg()[0]:.2f}",
        flush=True,
    )
    results: dict[str, list[tuple[float, float]]] = {name: [] for name in trees}
    for index in range(args.rounds):
        order = list(trees) if index % 2 == 0 else list(reversed(trees))
        for name in order:
            epochs_per_s, cpu_us = _one(trees[name], args)
            results[name].append((epochs_per_s, cpu_us))
            print(
                f"round {index + 1} {name:10s} {epochs_per_s:7.0f} epochs/s  {cpu_us:7.1f} us server CPU per epoch  "
                f"load average {os.getloadavg()[0]:.2f}",
                flush=True,
            )
    for name, rows in results.items():
        print(
            f"{name:10s} medians: {statistics.median(r[0] for r in rows):.0f} epochs/s, "
            f"{statistics.median(r[1] for r in rows):.1f} us server CPU per epoch"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
