"""Benchmark: the real service under load, beside a floor app and the bare filter, in one run.

Starts ``edgepos serve`` on free loopback ports (1 worker on the default in-process store, and
2 workers on a SQLite store in a temporary directory) and ``floor_app.py`` with 1 and 2 workers
(the same request schemas parsed, fixed fixes written by the service's own code, no filter), all
at once. Against each in turn it runs the load test as an open loop of 10, 50 and 100 vehicles at
20 Hz sending 20-epoch batches (one batch per vehicle per second). Then the closed loop (each
vehicle sends its next batch as soon as the last is answered), for capacity, in rounds: every
round runs every target once, so that a service and its floor are measured close together under
the same background load of a shared machine. It also times the rsu_imu pipeline in-process (the
filter alone).

Printed: a table of epochs/s and p50/p95/p99 latency per configuration; the ratio of the service's
closed-loop epochs/s to the floor's with the same number of workers, 20-epoch batches, per round
and its median (target >= 0.25: the filter, not the web layer, should be what costs); and the p99
latency at 100 vehicles x 20 Hz batched at 1 Hz (target < 100 ms with no errors); with the
machine's core count and load. The load generator runs in this process on the same cores as the
servers, and reports its own lateness.

    python bench/service_load.py [--duration S] [--saturate-duration S] [--rounds N] [--sizes 10,50,100]
        [--targets "service 1w memory,floor 1w"] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edgepos.core.compiled import warm_up as warm_up_kernels
from edgepos.loadgen import common
from edgepos.loadgen.loadtest import LoadConfig, LoadReport, run_load
from edgepos.loadgen.localserver import PORT_PLACEHOLDER, clean_environment, running, serve_command
from edgepos.pipelines.base import InitialState
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment

BENCH_DIR = Path(__file__).resolve().parent
ADMIN_KEY = "bench-admin-key-" + os.urandom(8).hex()
RATE_HZ = 20.0
BATCH_EPOCHS = 20
SATURATE_VEHICLES = 20
RATIO_TARGET = 0.25
P99_TARGET_MS = 100.0
P99_VEHICLES = 100
TARGETS = ("service 1w memory", "service 2w sqlite", "floor 1w", "floor 2w")


@dataclass
class Row:
    target: str
    mode: str
    vehicles: int
    report: LoadReport

    def cells(self) -> list[str]:
        data = self.report.to_json()
        latency = data["latency_ms"]
        offered = data["config"]["offered_epochs_per_s"]
        return [
            self.target,
            self.mode,
            str(self.vehicles),
            "-" if offered is None else f"{offered:.0f}",
            f"{data['epochs_per_s']:.0f}",
            f"{data['requests_per_s']:.1f}",
            *(f"{latency[q]:.1f}" if latency[q] is not None else "-" for q in ("p50", "p95", "p99")),
            str(data["errors"]),
            str(data["lateness"]["late_batches"]) if offered is not None else "-",
            f"{data['lateness']['loop_lag_p99_ms']:.1f}"
            if data["lateness"]["loop_lag_p99_ms"] is not None
            else "-",
        ]


HEADER = [
    "target",
    "mode",
    "vehicles",
    "offered ep/s",
    "epochs/s",
    "req/s",
    "p50 ms",
    "p95 ms",
    "p99 ms",
    "errors",
    "late",
    "gen lag p99 ms",
]


def table(rows: list[Row]) -> str:
    cells = [HEADER] + [row.cells() for row in rows]
    widths = [max(len(line[i]) for line in cells) for i in range(len(HEADER))]
    lines = [
        "  ".join(
            cell.rjust(width) if i > 1 else cell.ljust(width)
            for i, (cell, width) in enumerate(zip(line, widths))
        )
        for line in cells
    ]
    lines.insert(1, "  ".join("-" * width for width in widths))
    return "\n".join(lines)


def load(url: str, vehicles: int, duration: float, saturate: bool) -> LoadReport:
    config = LoadConfig(
        url=url,
        vehicles=vehicles,
        rate=RATE_HZ,
        batch=BATCH_EPOCHS,
        duration=duration,
        admin_key=ADMIN_KEY,
        saturate=saturate,
        timeout=30.0,
    )
    return asyncio.run(run_load(config))


def open_loops(name: str, url: str, sizes: list[int], duration: float) -> list[Row]:
    rows = []
    for vehicles in sizes:
        report = load(url, vehicles, duration, saturate=False)
        rows.append(Row(name, "open loop", vehicles, report))
        print(
            f"  {name}: {vehicles} vehicles open loop: {report.epochs_per_s:.0f} epochs/s, "
            f"p99 {report.latency(99) or float('nan'):.1f} ms, {report.errors} errors",
            flush=True,
        )
    return rows


def closed_loops(urls: dict[str, str], rounds: int, duration: float) -> list[Row]:
    """Each round runs the closed loop on every target in turn, so that a service and its floor are
    measured minutes apart at most, under the same background load of a shared machine."""
    rows = []
    for number in range(1, rounds + 1):
        for name, url in urls.items():
            report = load(url, SATURATE_VEHICLES, duration, saturate=True)
            rows.append(Row(name, f"closed loop {number}/{rounds}", SATURATE_VEHICLES, report))
            print(f"  {name}: closed loop {number}/{rounds}: {report.epochs_per_s:.0f} epochs/s", flush=True)
    return rows


def filter_alone(seconds: float = 3.0) -> float:
    """Epochs/s of the rsu_imu pipeline in this process on one core, 20-epoch batches (after the
    kernels are compiled or loaded from numba's cache, which the timing must not include)."""
    warm_up_kernels()
    scenario = rsu_imu_paper_scenario()
    pipeline = get_pipeline("rsu_imu")
    options = pipeline.resolve_options(None)
    start = common.initial_state(scenario)
    epochs = common.vehicle_epochs(scenario, 0, 0)
    env = environment(scenario)
    done, began = 0, time.perf_counter()
    while time.perf_counter() - began < seconds:
        state = pipeline.create(options, InitialState(start.x, start.y, start.vx, start.vy))
        for first in range(0, len(epochs), BATCH_EPOCHS):
            batch = [o for epoch in epochs[first : first + BATCH_EPOCHS] for o in epoch]
            _, state = pipeline.process(state, batch, env)
            done += len(epochs[first : first + BATCH_EPOCHS])
            if time.perf_counter() - began >= seconds:
                break
    return done / (time.perf_counter() - began)


def floor_command(workers: int) -> list[str]:
    return [
        sys.executable,
        str(BENCH_DIR / "floor_app.py"),
        "--port",
        PORT_PLACEHOLDER,
        "--workers",
        str(workers),
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=15.0, help="seconds per open-loop run (default 15)")
    parser.add_argument("--saturate-duration", type=float, default=10.0, help="seconds per closed-loop run")
    parser.add_argument("--rounds", type=int, default=3, help="closed-loop rounds over the targets")
    parser.add_argument("--sizes", default="10,50,100", help="open-loop vehicle counts (default 10,50,100)")
    parser.add_argument("--json", type=Path, default=None, help="also write every figure as JSON")
    parser.add_argument(
        "--targets", default=None, help=f"comma-separated subset of: {', '.join(TARGETS)} (default: all)"
    )
    args = parser.parse_args()
    wanted = None if args.targets is None else set(args.targets.split(","))
    sizes = [int(size) for size in args.sizes.split(",")]
    began = time.perf_counter()
    load_before = os.getloadavg()
    print(
        f"edgepos service load benchmark: {os.cpu_count()} cores, {platform.python_implementation()} "
        f"{platform.python_version()}, load average {load_before[0]:.2f} at start",
        flush=True,
    )
    print(
        f"open loop: vehicles x {RATE_HZ:g} Hz in {BATCH_EPOCHS}-epoch batches (1 batch/s each), "
        f"{args.duration:g} s; closed loop: {SATURATE_VEHICLES} vehicles, {args.saturate_duration:g} s, "
        f"{args.rounds} rounds",
        flush=True,
    )

    alone = filter_alone()
    print(f"  filter alone (in-process, one core): {alone:.0f} epochs/s", flush=True)
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="edgepos-bench-") as tmp:
        workdir = Path(tmp)
        env = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
            EDGEPOS_RATE_LIMIT_PER_S="0",  # capacity, not policy: no 429s in the closed loops
        )
        targets = [
            ("service 1w memory", serve_command(1), env),
            (
                "service 2w sqlite",
                serve_command(2),
                {**env, "EDGEPOS_STORE": f"sqlite:///{workdir / 'edgepos.db'}"},
            ),
            ("floor 1w", floor_command(1), env),
            ("floor 2w", floor_command(2), env),
        ]
        with contextlib.ExitStack() as servers:
            urls = {}
            for name, command, environment in targets:
                if wanted is None or name in wanted:
                    log_path = workdir / f"{name.replace(' ', '-')}.log"
                    urls[name] = servers.enter_context(running(command, environment, log_path))
            for name, url in urls.items():
                rows.extend(open_loops(name, url, sizes, args.duration))
            rows.extend(closed_loops(urls, args.rounds, args.saturate_duration))

    print()
    print(table(rows))
    closed: dict[str, list[float]] = {}
    for row in rows:
        if row.mode.startswith("closed loop"):
            closed.setdefault(row.target, []).append(row.report.epochs_per_s)
    print()
    print(
        f"cores: {os.cpu_count()}; load average {load_before[0]:.2f} before, {os.getloadavg()[0]:.2f} after; "
        f"filter alone {alone:.0f} epochs/s on one core"
    )
    verdicts: dict[str, Any] = {}
    for name, floor_name in (("service 1w memory", "floor 1w"), ("service 2w sqlite", "floor 2w")):
        if name not in closed or floor_name not in closed:
            continue
        rounds = [service / floor for service, floor in zip(closed[name], closed[floor_name])]
        ratio = statistics.median(rounds)
        verdicts[f"ratio {name}"] = ratio
        print(
            f"ratio service/floor, {BATCH_EPOCHS}-epoch batches, {name} / {floor_name}: median of rounds "
            f"{', '.join(f'{r:.2f}' for r in rounds)} = {ratio:.2f} (median epochs/s "
            f"{statistics.median(closed[name]):.0f} / {statistics.median(closed[floor_name]):.0f}; "
            f"target >= {RATIO_TARGET}) {'PASS' if ratio >= RATIO_TARGET else 'FAIL'}"
        )
    for row in rows:
        if row.mode == "open loop" and row.vehicles == P99_VEHICLES and row.target.startswith("service"):
            p99 = row.report.latency(99)
            ok = p99 is not None and p99 < P99_TARGET_MS and row.report.errors == 0
            verdicts[f"p99 {row.target}"] = p99
            print(
                f"p99 at {P99_VEHICLES} vehicles x {RATE_HZ:g} Hz batched at 1 Hz, {row.target}: "
                f"{p99 if p99 is not None else float('nan'):.1f} ms, {row.report.errors} errors "
                f"(target < {P99_TARGET_MS:g} ms, no errors) {'PASS' if ok else 'FAIL'}"
            )
    print(f"whole benchmark: {time.perf_counter() - began:.0f} s")
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {
                    "cores": os.cpu_count(),
                    "load_average_start": load_before[0],
                    "filter_alone_epochs_per_s": alone,
                    "runs": [
                        {"target": r.target, "mode": r.mode, "vehicles": r.vehicles, **r.report.to_json()}
                        for r in rows
                    ],
                    "verdicts": verdicts,
                },
                indent=2,
            )
            + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
