"""Benchmark: one light vehicle beside four heavy ones, on a real server.

Four ``gnss_tight`` sessions (UPF with the most particles a session may have) send the heaviest batch
the service accepts (real pseudoranges of tests/data/gnss-rover, as many epochs as the CPU budget
admits), back to back, while one ``rsu_imu`` vehicle sends one-epoch batches of the paper scenario on a
20 Hz schedule. Printed per server configuration: the share of the light vehicle's schedule answered
by the end of the run, its latency (from each batch's scheduled time, so lateness counts) at p50 and
p99, and the heavy vehicles' batches per second; with the machine's load average.

Configurations, started one after another on loopback:
  * 1 worker, in-process store, every batch on the one filter thread as before the scheduler's lanes
    (EDGEPOS_SCHEDULER_SLICE_MS=10000, EDGEPOS_HEAVY_WORKERS=0, EDGEPOS_LIGHT_LANE=thread; vehicles still
    served in turn);
  * 1 worker, in-process store, heavy batches on a second thread (EDGEPOS_HEAVY_WORKERS=0);
  * 1 worker, in-process store, heavy batches in a worker process (the default);
  * 2 workers on Redis (when redis-server is installed), the default lanes.
Targets (the fair-share issue): 1 worker >= 80 % of the schedule and p99 <= 250 ms; 2 workers p99 <= 100 ms.

    python bench/fairness.py [--duration S] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import math
import os
import platform
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from edgepos.core.observations import PseudorangeObservation
from edgepos.loadgen import common
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command
from edgepos.pipelines import cost
from edgepos.pipelines.gnss_options import OPTION_SPECS as GNSS_OPTIONS
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs
from gnss_api import load_epochs  # the GNSS bench's reading of the recording (bench/ is on sys.path)

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "gnss-rover"
ADMIN_KEY = "bench-admin-key-" + os.urandom(8).hex()
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
LIGHT_RATE_HZ = 20.0
HEAVY_VEHICLES = 4


def _max_particles(budget_s: float) -> int:
    """The most UPF particles a session may have: the option's maximum, or fewer when one epoch of the most
    pseudoranges accepted would not fit the budget (the server refuses such a session)."""
    spec = next(spec for spec in GNSS_OPTIONS if spec.name == "particles")
    assert spec.maximum is not None
    return min(int(spec.maximum), cost.max_particles("upf", budget_s))


def gnss_epochs() -> list[list[dict[str, Any]]]:
    """Every epoch of the rover recording as pseudorange measurements (GPS + BeiDou)."""
    return load_epochs(10**6, "GC")


def heaviest_epochs(options: dict[str, Any], epochs: list[list[dict[str, Any]]], budget_s: float) -> int:
    """How many consecutive epochs the service admits in one batch for these options (its own cost model)."""
    count = 1
    while count < len(epochs):
        batch = [
            PseudorangeObservation(m["t"], m["system"], m["prn"], m["pseudorange_m"], m["cn0_dbhz"])
            for epoch in epochs[: count + 1]
            for m in epoch
        ]
        if cost.batch_cost_s("gnss_tight", options, batch) > budget_s:
            break
        count += 1
    return count


def light_batches(count: int) -> list[list[dict[str, Any]]]:
    scenario = rsu_imu_paper_scenario()
    out = []
    for epoch in list(rsu_imu_epochs(scenario, np.random.default_rng(3)))[:count]:
        items = []
        for o in epoch:
            if hasattr(o, "rsu_id"):
                items.append(
                    {"type": "rsu", "t": o.t, "rsu_id": o.rsu_id, "range": o.range, "bearing": o.bearing}
                )
            else:
                items.append({"type": "gyro", "t": o.t, "yaw_rate": o.yaw_rate})
        out.append(items)
    return out


@dataclass
class Figures:
    scheduled: int = 0
    answered: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    latencies_ms: list[float] = field(default_factory=list)
    heavy_batches: int = 0
    heavy_errors: dict[str, int] = field(default_factory=dict)


async def _open(
    client: httpx.AsyncClient, vehicle: str, pipeline: str, options: dict[str, Any], initial: Any = None
) -> tuple[str, dict[str, str]]:
    body: dict[str, Any] = {"vehicle_id": vehicle, "pipeline": pipeline, "options": options}
    if initial is not None:
        body["initial_state"] = initial
    response = await client.post("/v1/sessions", json=body, headers=ADMIN)
    response.raise_for_status()
    created = response.json()
    return created["session_id"], {"Authorization": f"Bearer {created['token']}"}


async def heavy_vehicle(
    url: str,
    index: int,
    options: dict[str, Any],
    batches: list[list[dict[str, Any]]],
    stop_at: float,
    figures: Figures,
) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=120.0) as client:
        session_id, token = await _open(client, f"heavy-{index}", "gnss_tight", options)
        seq = 0
        while time.monotonic() < stop_at:
            if seq == len(batches):  # the recording is used up: start the vehicle again
                session_id, token = await _open(client, f"heavy-{index}", "gnss_tight", options)
                seq = 0
            seq += 1
            response = await client.post(
                f"/v1/sessions/{session_id}/batches",
                json={"seq": seq, "measurements": batches[seq - 1]},
                headers=token,
            )
            if response.status_code == 200:
                figures.heavy_batches += 1
            else:
                code = str(response.status_code)
                figures.heavy_errors[code] = figures.heavy_errors.get(code, 0) + 1
                if response.status_code != 429:
                    seq -= 1
                await asyncio.sleep(0.05)


async def light_vehicle(
    url: str, batches: list[list[dict[str, Any]]], start: float, stop_at: float, figures: Figures
) -> None:
    start_state = common.initial_state(rsu_imu_paper_scenario())
    initial = {"x": start_state.x, "y": start_state.y, "vx": start_state.vx, "vy": start_state.vy}
    async with httpx.AsyncClient(base_url=url, timeout=60.0) as client:
        session_id, token = await _open(client, "light-1", "rsu_imu", {}, initial)
        period = 1.0 / LIGHT_RATE_HZ
        figures.scheduled = int((stop_at - start) / period)
        for number in range(figures.scheduled):
            due = start + number * period
            now = time.monotonic()
            if now >= stop_at:
                break
            if due > now:
                await asyncio.sleep(due - now)
            response = await client.post(
                f"/v1/sessions/{session_id}/batches",
                json={"seq": number + 1, "measurements": batches[number % len(batches)]},
                headers=token,
            )
            done = time.monotonic()
            if response.status_code == 200 and done <= stop_at:
                figures.answered += 1
                figures.latencies_ms.append((done - due) * 1000.0)
            elif response.status_code != 200:
                code = str(response.status_code)
                figures.errors[code] = figures.errors.get(code, 0) + 1
                if response.status_code >= 400:
                    return


async def drive(url: str, duration: float, budget_s: float) -> tuple[Figures, dict[str, Any]]:
    async with httpx.AsyncClient(base_url=url, timeout=60.0) as client:
        nav = (DATA / "broadcast-nav.rnx").read_text()
        response = await client.put(
            "/v1/ephemerides", content=nav, headers={**ADMIN, "Content-Type": "text/plain"}
        )
        response.raise_for_status()
    options = {"filter": "upf", "particles": _max_particles(budget_s), "systems": ["G", "C"], "seed": 1}
    epochs = gnss_epochs()
    per_batch = heaviest_epochs(options, epochs, budget_s)
    batches = [
        list(itertools.chain.from_iterable(epochs[k : k + per_batch]))
        for k in range(0, len(epochs) - per_batch + 1, per_batch)
    ]
    light = light_batches(int(duration * LIGHT_RATE_HZ) + 1)
    figures = Figures()
    start = time.monotonic() + 1.0
    stop_at = start + duration
    await asyncio.gather(
        light_vehicle(url, light, start, stop_at, figures),
        *(heavy_vehicle(url, index, options, batches, stop_at, figures) for index in range(HEAVY_VEHICLES)),
    )
    return figures, {
        "particles": options["particles"],
        "epochs_per_heavy_batch": per_batch,
        "pseudoranges_per_heavy_batch": len(batches[0]),
    }


def _p(values: list[float], q: float) -> float:
    if not values:
        return math.nan
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, math.ceil(q * len(ordered)) - 1)]


def run_target(
    name: str, workers: int, store: str, extra: dict[str, str], duration: float, workdir: Path
) -> dict[str, Any]:
    environment = clean_environment(
        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
        EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
        EDGEPOS_LOG_LEVEL="warning",
        EDGEPOS_RATE_LIMIT_PER_S="0",
        EDGEPOS_DEMO_RSUS="true",
        EDGEPOS_STORE=store,
        **extra,
    )
    budget_s = float(extra.get("EDGEPOS_BATCH_CPU_BUDGET_MS", "50")) / 1000.0
    with running(serve_command(workers), environment, workdir / f"{name}.log") as url:
        figures, heavy = asyncio.run(drive(url, duration, budget_s))
    load = os.getloadavg()
    return {
        "target": name,
        "light_completed": figures.answered / max(1, figures.scheduled),
        "light_p50_ms": _p(figures.latencies_ms, 0.50),
        "light_p99_ms": _p(figures.latencies_ms, 0.99),
        "light_errors": figures.errors,
        "heavy_batches_per_s": figures.heavy_batches / duration,
        "heavy_errors": figures.heavy_errors,
        "load_average": [round(x, 2) for x in load],
        **heavy,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--duration", type=float, default=15.0, help="seconds of load per configuration (default 15)"
    )
    parser.add_argument("--json", type=Path, default=None, help="write the figures as JSON")
    parser.add_argument(
        "--budget-ms",
        type=float,
        default=50.0,
        help="EDGEPOS_BATCH_CPU_BUDGET_MS of every server (default 50, the service's); a larger budget admits "
        "heavier batches and shows what the heavy lane's processes buy",
    )
    args = parser.parse_args(argv)
    budget = {"EDGEPOS_BATCH_CPU_BUDGET_MS": f"{args.budget_ms:g}"}
    rows = []
    before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="edgepos-fairness-") as tmp:
        workdir = Path(tmp)
        one_lane = {
            **budget,
            "EDGEPOS_HEAVY_WORKERS": "0",
            "EDGEPOS_SCHEDULER_SLICE_MS": "10000",
            "EDGEPOS_LIGHT_LANE": "thread",
        }
        rows.append(
            run_target("1 worker, one lane (as before)", 1, "memory", one_lane, args.duration, workdir)
        )
        rows.append(
            run_target(
                "1 worker, heavy on a thread",
                1,
                "memory",
                {**budget, "EDGEPOS_HEAVY_WORKERS": "0"},
                args.duration,
                workdir,
            )
        )
        rows.append(run_target("1 worker, heavy in a process", 1, "memory", budget, args.duration, workdir))
        binary = redis_binary()
        if binary is not None:
            with RedisServer(
                binary, workdir / "redis", "--save", "", "--appendonly", "yes", "--appendfsync", "everysec"
            ) as redis:
                rows.append(
                    run_target("2 workers on Redis", 2, redis.url("fair:"), budget, args.duration, workdir)
                )
        else:
            print("redis-server is not installed: the 2-worker row is skipped", file=sys.stderr)
    print(f"machine: {os.cpu_count()} cores, {platform.python_implementation()} {platform.python_version()}")
    print(f"CPU budget per batch: {args.budget_ms:g} ms; load average before: {before[0]:.2f}")
    print(
        f"heavy vehicles: {HEAVY_VEHICLES} x UPF {rows[0]['particles']} particles, {rows[0]['epochs_per_heavy_batch']} "
        f"epochs ({rows[0]['pseudoranges_per_heavy_batch']} pseudoranges) per batch, back to back; "
        f"light vehicle: one-epoch rsu_imu batches at {LIGHT_RATE_HZ:g} Hz for {args.duration:g} s"
    )
    print(
        f"{'configuration':34} {'light done':>10} {'p50 ms':>8} {'p99 ms':>8} {'heavy b/s':>9}  load avg   errors"
    )
    for row in rows:
        print(
            f"{row['target']:34} {row['light_completed']:>10.1%} {row['light_p50_ms']:>8.1f} {row['light_p99_ms']:>8.1f} "
            f"{row['heavy_batches_per_s']:>9.1f}  {row['load_average'][0]:<9} light {row['light_errors'] or '-'} heavy {row['heavy_errors'] or '-'}"
        )
    if args.json is not None:
        args.json.write_text(json.dumps({"rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
