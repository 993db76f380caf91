"""Benchmark: the service against its floor under wrk (a C load generator), interleaved rounds in one run.

The figures of the performance issue: closed loops of N vehicles (one wrk thread and connection each)
sending ``rsu_imu`` batches of 20 epochs of the RSU + IMU paper's scenario (4 RSUs + gyro per epoch),
timestamps jittered by a few milliseconds as real clocks are, against

* the service (``edgepos serve``, the demo RSU map, rate limit off: capacity, not policy) on the
  in-process store, on a ``redis-server`` started here (append-only file, ``appendfsync everysec``), or,
  with ``--store memory,redis``, on each in turn (then also Redis ÷ in-process per round);
* the floor (``bench/floor_app.py``): the same routes and request schemas, fixed answers of the same
  shape, no filter, no store.

Each service run also prints the server's own CPU time per epoch (its processes', from /proc), which a
busy machine disturbs far less than the epochs per second.

Each round runs every target once, so a service and its floor are measured close together under the
same background load; the ratio service ÷ floor is taken per round. wrk's latency percentiles include
the few session creations (one per 40 batches per vehicle). wrk is Debian's package (``make bench``
installs it).

With ``--light-lane loop,thread`` each store's service is measured with the light lane on the event loop
and on the filter thread (``EDGEPOS_LIGHT_LANE``; the service's default), and thread ÷ loop printed per round.

    python bench/wrk_load.py [--workers 1] [--store memory|redis|memory,redis] [--light-lane loop|thread|loop,thread]
        [--vehicles 16] [--duration 10] [--rounds 3] [--batch 20] [--jitter-ms 3] [--json FILE] [--budget RATIO]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import capacity_budget
import numpy as np
import redis as redis_client
from edgepos.loadgen import common
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import (
    PORT_PLACEHOLDER,
    clean_environment,
    running,
    serve_command,
    service_cpu_s,
)
from edgepos.sim.scenarios import rsu_imu_paper_scenario

BENCH_DIR = Path(__file__).resolve().parent
ADMIN_KEY = "wrk-benchmark-admin-key"


def write_batches(directory: Path, batch_epochs: int, jitter_s: float, seed: int) -> int:
    """The scenario's epochs as batch bodies (one JSON line each, ``"seq":0`` for the script to set) and
    the session-creation body; returns the number of batches per trip."""
    scenario = rsu_imu_paper_scenario()
    rng = np.random.default_rng(seed)
    epochs = common.vehicle_epochs(scenario, seed, 0)
    shifts = rng.uniform(-jitter_s, jitter_s, len(epochs))  # period 50 ms: the order is kept
    lines = []
    for start in range(0, len(epochs) - batch_epochs + 1, batch_epochs):
        measurements = []
        for shift, epoch in zip(shifts[start : start + batch_epochs], epochs[start : start + batch_epochs]):
            for observation in epoch:
                wire = common.to_wire(observation).model_dump(mode="json", exclude_none=True)
                wire["t"] = round(float(observation.t + shift), 6)
                measurements.append(wire)
        lines.append(json.dumps({"seq": 0, "measurements": measurements}, separators=(",", ":")))
    (directory / "batches.jsonl").write_text("\n".join(lines) + "\n")
    initial = common.initial_state(scenario)
    create = {
        "vehicle_id": "wrk-VEHICLE",
        "pipeline": "rsu_imu",
        "initial_state": {"x": initial.x, "y": initial.y, "vx": initial.vx, "vy": initial.vy},
    }
    (directory / "create.json").write_text(json.dumps(create, separators=(",", ":")))
    return len(lines)


def run_wrk(url: str, directory: Path, vehicles: int, duration_s: float) -> dict[str, Any]:
    """One closed-loop wrk run; the totals its script prints."""
    command = [
        "wrk", "-t", str(vehicles), "-c", str(vehicles), "-d", f"{duration_s:g}s", "--timeout", "10s",
        "-s", str(BENCH_DIR / "wrk_batches.lua"), url, "--", str(directory), ADMIN_KEY,
    ]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    output = subprocess.run(
        command, capture_output=True, text=True, check=True, timeout=duration_s + 60
    ).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # wrk's own, once waited for
    line = next(line for line in output.splitlines() if line.startswith("WRK_RESULT "))
    result: dict[str, Any] = json.loads(line.removeprefix("WRK_RESULT "))
    seconds = result["duration_us"] / 1e6
    result["epochs_per_s"] = result["epochs"] / seconds
    wrk_cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    result["wrk_cpu_us_per_epoch"] = wrk_cpu_s / max(1, result["epochs"]) * 1e6
    return result


def redis_cpu_s(url: str) -> float:
    """CPU seconds redis-server (and its forks: AOF rewrites) has used so far (``INFO cpu``)."""
    client = redis_client.Redis.from_url(url.split("?", 1)[0])  # the query is the service's key prefix
    try:
        info = client.info("cpu")
    finally:
        client.close()
    keys = ("used_cpu_sys", "used_cpu_user", "used_cpu_sys_children", "used_cpu_user_children")
    return float(sum(info[key] for key in keys))


STORES = ("memory", "redis")
LANES = ("loop", "thread")


def _choices(allowed: tuple[str, ...], what: str) -> Any:
    def parse(text: str) -> tuple[str, ...]:
        chosen = tuple(dict.fromkeys(part.strip() for part in text.split(",") if part.strip()))
        if not chosen or any(choice not in allowed for choice in chosen):
            raise argparse.ArgumentTypeError(f"comma-separated {what} of {', '.join(allowed)}, got {text!r}")
        return chosen

    return parse


_stores = _choices(STORES, "stores")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument(
        "--store",
        type=_stores,
        default=("memory",),
        help="memory, redis, or both comma-separated (each measured in every round)",
    )
    parser.add_argument(
        "--light-lane",
        type=_choices(LANES, "light lanes"),
        default=("thread",),
        help="thread (the service's default), loop, or both comma-separated (EDGEPOS_LIGHT_LANE; each measured in every round)",
    )
    parser.add_argument("--vehicles", type=int, default=16)
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per run")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--batch", type=int, default=20, help="epochs per batch")
    parser.add_argument("--jitter-ms", type=float, default=3.0, help="timestamp jitter, uniform +-")
    parser.add_argument("--json", type=Path)
    parser.add_argument(
        "--budget",
        type=float,
        metavar="RATIO",
        help="also print the CPU budget an epoch at RATIO of the floor's epochs/s and what every epoch costs "
        "whatever the service does (bench/capacity_budget.py)",
    )
    args = parser.parse_args()
    if shutil.which("wrk") is None:
        print("wrk is not installed: `make wrk` (Debian package) installs it", file=sys.stderr)
        return 2
    load_before = os.getloadavg()[0]
    print(
        f"wrk load: {os.cpu_count()} cores, {platform.python_implementation()} {platform.python_version()}, "
        f"{args.vehicles} vehicles closed loop, {args.batch}-epoch batches, jitter +-{args.jitter_ms:g} ms, "
        f"{args.workers} worker(s), store {','.join(args.store)}, light lane {','.join(args.light_lane)}, "
        f"{args.duration:g} s x {args.rounds} rounds, "
        f"load average {load_before:.2f} at start",
        flush=True,
    )
    services = {
        (store, lane): " ".join(
            [
                "service",
                *([store] if len(args.store) > 1 else []),
                *([lane] if len(args.light_lane) > 1 else []),
            ]
        )
        for store in args.store
        for lane in args.light_lane
    }
    results: dict[str, list[dict[str, Any]]] = {name: [] for name in [*services.values(), "floor"]}
    with tempfile.TemporaryDirectory(prefix="edgepos-wrk-") as tmp, contextlib.ExitStack() as stack:
        workdir = Path(tmp)
        write_batches(workdir, args.batch, args.jitter_ms / 1e3, seed=1)
        env = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
            EDGEPOS_DEMO_RSUS="true",
            EDGEPOS_RATE_LIMIT_PER_S="0",  # capacity, not policy
        )
        environments = {"memory": env}
        if "redis" in args.store:
            binary = redis_binary()
            if binary is None:
                print("redis-server is not installed: `make redis-server` installs it", file=sys.stderr)
                return 2
            redis = stack.enter_context(
                RedisServer(binary, workdir / "redis", "--appendonly", "yes", "--appendfsync", "everysec")
            )
            environments["redis"] = {**env, "EDGEPOS_STORE": redis.url(prefix="wrk")}
        floor = [sys.executable, str(BENCH_DIR / "floor_app.py"), "--port", PORT_PLACEHOLDER]
        floor += ["--workers", str(args.workers)]
        targets = {
            name: (serve_command(args.workers), {**environments[store], "EDGEPOS_LIGHT_LANE": lane})
            for (store, lane), name in services.items()
        }
        targets["floor"] = (floor, env)
        for round_index in range(args.rounds):
            for name, (command, target_env) in targets.items():
                log = workdir / f"{name.replace(' ', '-')}.log"
                with running(command, target_env, log, ready_timeout_s=300.0) as url:
                    run_wrk(
                        url, workdir, args.vehicles, min(2.0, args.duration)
                    )  # warm-up (compiles, caches)
                    marker = b"floor_app.py" if name == "floor" else b"serve"
                    store_url = target_env.get("EDGEPOS_STORE", "")
                    cpu_before = service_cpu_s(url, marker)
                    redis_before = redis_cpu_s(store_url) if store_url.startswith("redis") else None
                    result = run_wrk(url, workdir, args.vehicles, args.duration)
                    # the server's own CPU (its workers too): steadier than epochs/s
                    epochs = max(1, result["epochs"])
                    result["server_cpu_us_per_epoch"] = (
                        (service_cpu_s(url, marker) - cpu_before) / epochs * 1e6
                    )
                    if redis_before is not None:
                        result["redis_cpu_us_per_epoch"] = (
                            (redis_cpu_s(store_url) - redis_before) / epochs * 1e6
                        )
                results[name].append(result)
                redis_cpu = result.get("redis_cpu_us_per_epoch")
                print(
                    f"  round {round_index + 1} {name:21s} {result['epochs_per_s']:9.0f} epochs/s  "
                    f"p50 {result['p50_us'] / 1e3:6.1f} ms  p99 {result['p99_us'] / 1e3:6.1f} ms  "
                    f"errors {result['errors'] + result['socket_errors']}  CPU us/epoch: server "
                    f"{result['server_cpu_us_per_epoch']:6.1f}, wrk {result['wrk_cpu_us_per_epoch']:5.1f}"
                    + (f", redis-server {redis_cpu:5.1f}" if redis_cpu is not None else ""),
                    flush=True,
                )
    ratios: dict[str, list[float]] = {}
    floor_rate = statistics.median(r["epochs_per_s"] for r in results["floor"])
    for name in services.values():
        ratios[f"{name} / floor"] = _per_round(results[name], results["floor"])
        service = statistics.median(r["epochs_per_s"] for r in results[name])
        p99 = statistics.median(r["p99_us"] for r in results[name]) / 1e3
        errors = sum(r["errors"] + r["socket_errors"] for r in results[name])
        print(
            f"{name} {service:.0f} epochs/s (p99 {p99:.1f} ms, {errors} errors), floor {floor_rate:.0f} "
            f"(medians of rounds); {name} / floor per round: "
            + ", ".join(f"{ratio:.2f}" for ratio in ratios[f"{name} / floor"])
        )
    for lane in args.light_lane if len(args.store) > 1 else ():
        suffix = f" ({lane})" if len(args.light_lane) > 1 else ""
        per_round = ratios["redis / memory" + suffix] = _per_round(
            results[services["redis", lane]], results[services["memory", lane]]
        )
        print(f"Redis / in-process{suffix} per round: " + ", ".join(f"{ratio:.2f}" for ratio in per_round))
    for store in args.store if len(args.light_lane) > 1 else ():
        suffix = f" ({store})" if len(args.store) > 1 else ""
        per_round = ratios["thread / loop" + suffix] = _per_round(
            results[services[store, "thread"]], results[services[store, "loop"]]
        )
        print(
            f"light lane thread / loop{suffix} per round: " + ", ".join(f"{ratio:.2f}" for ratio in per_round)
        )
        cpu_ratios = ratios["thread / loop server CPU per epoch" + suffix] = [
            a["server_cpu_us_per_epoch"] / b["server_cpu_us_per_epoch"]
            for a, b in zip(results[services[store, "thread"]], results[services[store, "loop"]])
        ]
        print(
            f"server CPU per epoch, thread / loop{suffix} per round: "
            + ", ".join(f"{ratio:.2f}" for ratio in cpu_ratios)
        )
    cores = os.cpu_count() or 1
    print(
        f"CPU per epoch, medians of rounds (server + wrk + redis-server), and the epochs/s {cores} cores "
        "would serve if that were all they did:"
    )
    for name, runs in results.items():
        parts = [
            statistics.median(r.get(key, 0.0) for r in runs)
            for key in ("server_cpu_us_per_epoch", "wrk_cpu_us_per_epoch", "redis_cpu_us_per_epoch")
        ]
        print(
            f"  {name:21s} {sum(parts):6.1f} us = {parts[0]:.1f} + {parts[1]:.1f} + {parts[2]:.1f}"
            f"  -> {cores / sum(parts) * 1e6:8.0f} epochs/s"
        )
    print(f"load average {load_before:.2f} before, {os.getloadavg()[0]:.2f} after")
    budget: dict[str, float] = {}
    if args.budget:
        budget = capacity_budget.print_budget(
            args.budget, results["floor"], {name: results[name] for name in services.values()}, cores
        )
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "args": vars(args)
                    | {
                        "json": str(args.json),
                        "store": list(args.store),
                        "light_lane": list(args.light_lane),
                    },
                    "results": results,
                    "ratios": ratios,
                    "budget": budget,
                },
                indent=2,
            )
        )
    return 0


def _per_round(numerators: list[dict[str, Any]], denominators: list[dict[str, Any]]) -> list[float]:
    return [a["epochs_per_s"] / b["epochs_per_s"] for a, b in zip(numerators, denominators)]


if __name__ == "__main__":
    sys.exit(main())
