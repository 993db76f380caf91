"""Benchmark: a session's batches over HTTP (keep-alive POSTs) against the same batches over its WebSocket.

Starts ``edgepos serve`` (one worker, in-process store) on a free loopback port and drives it with
``--vehicles`` vehicles closed-loop: each sends its next rsu_imu batch as soon as the previous one is
answered, through the client package (``send_batch`` on its own keep-alive httpx connection, or
``websocket(session).send_batch`` on its own WebSocket), so both ways encode and parse alike. Batches
of 1 epoch and of 20 epochs (``--batches``), the paper scenario with each vehicle's own noise
(loadgen.common); a vehicle that reaches the scenario's end opens a new session (not timed). HTTP and
WebSocket runs alternate in interleaved rounds (the order flips every round), each ``--duration``
seconds. Printed per run: epochs/s, batches/s, p50/p99 latency (send to answer), and the CPU per epoch
of the service (its process, from /proc) and of the vehicles (this process: all vehicles share one
event loop, so on a small machine their client-side cost bounds the closed loop as much as the
server does); then per batch size the medians over the rounds and the ratios WebSocket / HTTP, the
core count and the load average. Loopback only.

    python bench/websocket.py [--vehicles N] [--batches 1,20] [--duration S] [--rounds R] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
from edgepos.loadgen import common
from edgepos.loadgen.localserver import clean_environment, running, serve_command, service_cpu_s
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos_client import AsyncEdgeposClient, Session

ADMIN_KEY = "ws-bench-admin-key-" + os.urandom(8).hex()
MODES = ("http", "ws")


class Vehicle:
    """One vehicle: its batches, its client (own connection), and its session's socket in ws mode."""

    def __init__(self, url: str, name: str, batches: list[list[common.WireMeasurement]], start: Any) -> None:
        limits = httpx.Limits(max_connections=1, max_keepalive_connections=1)
        self.client = AsyncEdgeposClient(url, ADMIN_KEY, timeout=30.0, retries=0, limits=limits)
        self.name = name
        self.batches = batches
        self.start = start
        self.session: Session | None = None
        self.position = 0

    async def new_trip(self) -> Session:
        self.session = await self.client.create_session(self.name, initial_state=self.start)
        self.position = 0
        return self.session

    async def run(self, mode: str, until: float, latencies: list[float], epochs: list[int]) -> None:
        """Send batches closed-loop until ``until`` (perf_counter); one latency per answered batch."""
        session = await self.new_trip()
        socket = self.client.websocket(session) if mode == "ws" else None
        try:
            while time.perf_counter() < until:
                if self.position >= len(self.batches):
                    if socket is not None:
                        await socket.close()
                    session = await self.new_trip()
                    socket = self.client.websocket(session) if mode == "ws" else None
                batch = self.batches[self.position]
                started = time.perf_counter()
                if socket is not None:
                    fixes = await socket.send_batch(batch)
                else:
                    fixes = await self.client.send_batch(session, batch)
                latencies.append(time.perf_counter() - started)
                epochs[0] += len(fixes)
                self.position += 1
        finally:
            if socket is not None:
                await socket.close()


async def _run(
    url: str, mode: str, batch_epochs: int, args: argparse.Namespace, label: str
) -> dict[str, Any]:
    scenario = rsu_imu_paper_scenario()
    start = common.initial_state(scenario)
    vehicles = [
        Vehicle(
            url,
            f"{label}-{v}",
            common.wire_batches(common.vehicle_epochs(scenario, 7, v), batch_epochs),
            start,
        )
        for v in range(args.vehicles)
    ]
    latencies: list[float] = []
    epochs = [0]
    try:
        if mode == "ws":  # the handshakes, like the HTTP connections, are not timed: open them first
            for vehicle in vehicles:
                session = await vehicle.new_trip()
                async with vehicle.client.websocket(session) as socket:
                    await socket.send_batch(vehicle.batches[0])
        else:
            for vehicle in vehicles:
                await vehicle.client.send_batch(await vehicle.new_trip(), vehicle.batches[0])
        cpu_before, own_before = service_cpu_s(url), time.process_time()
        began = time.perf_counter()
        until = began + args.duration
        await asyncio.gather(*(vehicle.run(mode, until, latencies, epochs) for vehicle in vehicles))
        elapsed = time.perf_counter() - began
        cpu_s, own_s = service_cpu_s(url) - cpu_before, time.process_time() - own_before
    finally:
        for vehicle in vehicles:
            await vehicle.client.close()
    return {
        "mode": mode,
        "batch_epochs": batch_epochs,
        "epochs_per_s": epochs[0] / elapsed,
        "batches_per_s": len(latencies) / elapsed,
        "p50_ms": 1e3 * (common.percentile(latencies, 50) or 0.0),
        "p99_ms": 1e3 * (common.percentile(latencies, 99) or 0.0),
        "service_cpu_us_per_epoch": 1e6 * cpu_s / max(1, epochs[0]),
        "client_cpu_us_per_epoch": 1e6 * own_s / max(1, epochs[0]),
        "batches": len(latencies),
    }


def _line(run: dict[str, Any]) -> str:
    return (
        f"{run['mode']:>4} {run['batch_epochs']:>2}-epoch: {run['epochs_per_s']:8.0f} epochs/s "
        f"{run['batches_per_s']:7.0f} batches/s  p50 {run['p50_ms']:6.2f} ms  p99 {run['p99_ms']:6.2f} ms  "
        f"CPU/epoch service {run['service_cpu_us_per_epoch']:5.0f} us, vehicles {run['client_cpu_us_per_epoch']:5.0f} us"
    )


def _summary(runs: list[dict[str, Any]], sizes: list[int]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for size in sizes:
        median = {
            mode: {
                key: statistics.median(
                    r[key] for r in runs if r["mode"] == mode and r["batch_epochs"] == size
                )
                for key in (
                    "epochs_per_s",
                    "p50_ms",
                    "p99_ms",
                    "service_cpu_us_per_epoch",
                    "client_cpu_us_per_epoch",
                )
            }
            for mode in MODES
        }
        ratio = {
            key: median["ws"][key] / median["http"][key] for key in median["http"] if median["http"][key]
        }
        out[f"{size}-epoch"] = {"median": median, "ws_over_http": ratio}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=16, help="vehicles sending closed-loop (default 16)")
    parser.add_argument("--batches", default="1,20", help="epochs per batch, comma-separated (default 1,20)")
    parser.add_argument("--duration", type=float, default=5.0, help="seconds per run (default 5)")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved HTTP/WebSocket rounds (default 3)")
    parser.add_argument("--json", type=Path, default=None, help="also write the runs and summary here")
    args = parser.parse_args()
    sizes = [int(part) for part in args.batches.split(",")]
    if args.vehicles < 1 or args.rounds < 1 or args.duration <= 0 or min(sizes) < 1:
        parser.error("--vehicles, --rounds, --duration and every batch size must be positive")
    environment = clean_environment(EDGEPOS_ADMIN_KEY=ADMIN_KEY, EDGEPOS_LOG_LEVEL="warning")
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as workdir:
        log = Path(workdir) / "server.log"
        with running(serve_command(1), environment, log, ready_timeout_s=300.0) as url:

            async def load_rsus() -> None:
                async with AsyncEdgeposClient(url, ADMIN_KEY) as admin:
                    await admin.put_rsus(common.scenario_rsus(rsu_imu_paper_scenario()))

            asyncio.run(load_rsus())
            for round_index in range(args.rounds):
                order = MODES if round_index % 2 == 0 else MODES[::-1]
                for size in sizes:
                    for mode in order:
                        label = f"wsb-{round_index}-{size}-{mode}"
                        run = asyncio.run(_run(url, mode, size, args, label))
                        runs.append(run)
                        print(f"round {round_index + 1} {_line(run)}", flush=True)
    summary = _summary(runs, sizes)
    print(
        f"\nmedians over {args.rounds} rounds, {args.vehicles} vehicles closed-loop, {args.duration:g} s per run:"
    )
    for size in sizes:
        entry = summary[f"{size}-epoch"]
        for mode in MODES:
            m = entry["median"][mode]
            print(
                f"  {mode:>4} {size:>2}-epoch: {m['epochs_per_s']:8.0f} epochs/s  p50 {m['p50_ms']:6.2f} ms  "
                f"p99 {m['p99_ms']:6.2f} ms  CPU/epoch service {m['service_cpu_us_per_epoch']:5.0f} us, "
                f"vehicles {m['client_cpu_us_per_epoch']:5.0f} us"
            )
        r = entry["ws_over_http"]
        print(
            f"  ws/http {size:>2}-epoch: epochs/s x{r['epochs_per_s']:.2f}  p50 x{r['p50_ms']:.2f}  "
            f"p99 x{r['p99_ms']:.2f}  CPU/epoch service x{r['service_cpu_us_per_epoch']:.2f}, "
            f"vehicles x{r['client_cpu_us_per_epoch']:.2f}"
        )
    load = os.getloadavg()
    print(f"cores {os.cpu_count()}, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {"args": vars(args) | {"json": str(args.json)}, "runs": runs, "summary": summary}, indent=2
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
