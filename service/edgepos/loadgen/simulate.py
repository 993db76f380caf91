"""``edgepos simulate``: drive a running server with simulated vehicles and score their fixes.

It loads the scenario's RSU map (PUT /v1/rsus, admin key), opens one session per vehicle started
at the true initial state (1 m, 1 m/s), and sends every vehicle's measurements (its own noise
stream: child i of the seed) in batches of B epochs, all vehicles at once through one async
client. ``--realtime`` sends each batch when its last epoch has happened on the scenario's clock;
the default sends as fast as the server answers. It ends with each vehicle's position and
velocity RMSE against the scenario's ground truth, and deletes the sessions it opened.

``--delay-fraction F --max-delay S``: the run three times over, as the vehicles' measurements would
reach the server in order, with a fraction F of the RSU measurements up to S seconds late
(``sim.delivery``: each batch holds what arrived since the previous one), and with those late ones
dropped; the errors are those of the last fix received per epoch (a revised fix replaces the earlier).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import httpx
import numpy as np
from edgepos_client import AsyncEdgeposClient, EdgeposError, Fix, RateLimited, Session, TooManySessions

from edgepos.cli_output import prepare_output, write_output
from edgepos.core.observations import Observation
from edgepos.loadgen import common, federated_sim, v2v_sim
from edgepos.sim.delivery import (
    LateDelivery,
    add_delivery_arguments,
    arrival_batches,
    arrival_times,
    delivery_from,
)
from edgepos.sim.scenarios import Scenario


@dataclass
class VehicleRun:
    """One simulated vehicle: its session, the fixes it got back, and its errors against the truth."""

    index: int
    vehicle_id: str
    session_id: str = ""
    fixes: list[Fix] = field(default_factory=list)
    error: str | None = None
    position_rmse: float | None = None
    velocity_rmse: float | None = None
    rate_limited: int = 0  # batches the server asked to send again later (429 with Retry-After)


#: A vehicle that is refused for its request rate this many times in a row gives up (the server is
#: configured for far fewer requests than the simulation sends, e.g. one-epoch batches with --fast).
MAX_RATE_LIMITED_IN_A_ROW = 20


@dataclass
class SimulationResult:
    scenario: str
    seed: int
    batch_epochs: int
    epochs: int
    vehicles: list[VehicleRun]
    elapsed_s: float

    @property
    def mean_position_rmse(self) -> float | None:
        return _mean([v.position_rmse for v in self.vehicles])

    @property
    def mean_velocity_rmse(self) -> float | None:
        return _mean([v.velocity_rmse for v in self.vehicles])

    def to_json(self) -> dict[str, object]:
        return {
            "scenario": self.scenario,
            "seed": self.seed,
            "batch_epochs": self.batch_epochs,
            "epochs": self.epochs,
            "elapsed_s": self.elapsed_s,
            "vehicles": [
                {
                    "vehicle_id": v.vehicle_id,
                    "session_id": v.session_id,
                    "fixes": len(v.fixes),
                    "position_rmse_m": v.position_rmse,
                    "velocity_rmse_m_s": v.velocity_rmse,
                    "rate_limited": v.rate_limited,
                    "error": v.error,
                }
                for v in self.vehicles
            ],
            "mean": {
                "position_rmse_m": self.mean_position_rmse,
                "velocity_rmse_m_s": self.mean_velocity_rmse,
            },
        }


def _mean(values: list[float | None]) -> float | None:
    present = [value for value in values if value is not None]
    return sum(present) / len(present) if present else None


def rmse(fixes: list[Fix], scenario: Scenario) -> tuple[float | None, float | None]:
    """Position (m) and velocity (m/s) RMSE of the last fix received for each epoch against the truth
    at its t (a revised fix replaces the earlier one of the same t); epochs whose fix has no estimate
    (uninitialised) are left out."""
    truth = scenario.truth
    latest = {fix.t: fix for fix in fixes}
    position, velocity = [], []
    for t, fix in latest.items():
        k = int(np.argmin(np.abs(truth.t - t)))  # the truth sample of the epoch (times are the truth's)
        if fix.x is not None and fix.y is not None:
            position.append((fix.x - truth.x[k]) ** 2 + (fix.y - truth.y[k]) ** 2)
        if fix.vx is not None and fix.vy is not None:
            velocity.append((fix.vx - truth.vx[k]) ** 2 + (fix.vy - truth.vy[k]) ** 2)
    return _rmse(position), _rmse(velocity)


class Progress:
    """The live one-line progress report on a stream (rewritten in place with a carriage return)."""

    def __init__(self, total_epochs: int, vehicles: int, stream: TextIO | None) -> None:
        self.total = total_epochs
        self.vehicles = vehicles
        self.stream = stream
        self.epochs = 0
        self.batches = 0
        self.started = time.perf_counter()

    def line(self) -> str:
        elapsed = time.perf_counter() - self.started
        share = 100.0 * self.epochs / self.total if self.total else 100.0
        return (
            f"simulate: {self.vehicles} vehicle(s), {self.epochs}/{self.total} epochs ({share:.0f} %), "
            f"{self.batches} batches, {elapsed:.1f} s, {self.epochs / max(elapsed, 1e-9):.0f} epochs/s"
        )

    @property
    def interactive(self) -> bool:
        return self.stream is not None and self.stream.isatty()

    def show(self, final: bool = False) -> None:
        """Rewrite the line on a terminal; elsewhere (logs, pipes) write whole lines."""
        if self.stream is None:
            return
        if self.interactive:
            self.stream.write("\r" + self.line() + ("\n" if final else ""))
        else:
            self.stream.write(self.line() + "\n")
        self.stream.flush()

    async def run(self) -> None:
        period_s = 0.25 if self.interactive else 2.0
        while True:
            await asyncio.sleep(period_s)
            self.show()


async def _drive(
    client: AsyncEdgeposClient,
    session: Session,
    run: VehicleRun,
    batches: list[list[common.WireMeasurement]],
    pace_s: float | None,
    started: float,
    progress: Progress,
) -> None:
    """Send one vehicle's batches in order; with ``pace_s`` each when its last epoch has happened."""
    sent_epochs = 0
    for batch in batches:
        epochs = len({measurement.t for measurement in batch})
        sent_epochs += epochs
        if pace_s is not None:
            await asyncio.sleep(max(0.0, started + sent_epochs * pace_s - time.perf_counter()))
        fixes = await _send_politely(client, session, batch, run)
        if fixes is None:
            return
        run.fixes.extend(fixes)
        progress.epochs += len(fixes)
        progress.batches += 1


async def _send_politely(
    client: AsyncEdgeposClient, session: Session, batch: list[common.WireMeasurement], run: VehicleRun
) -> list[Fix] | None:
    """Send one batch; a 429 for the request rate is waited out (its Retry-After, else 1 s) and the same
    batch sent again with the same seq, as a well-behaved vehicle does. None (and ``run.error``) on any
    other error, or after MAX_RATE_LIMITED_IN_A_ROW refusals in a row."""
    refusals = 0
    while True:
        try:
            return await client.send_batch(session, batch)
        except TooManySessions as error:
            run.error = str(error)
            return None
        except RateLimited as error:
            run.rate_limited += 1
            refusals += 1
            if refusals >= MAX_RATE_LIMITED_IN_A_ROW:
                run.error = f"{error} ({refusals} times in a row; giving up)"
                return None
            await asyncio.sleep(error.retry_after if error.retry_after is not None else 1.0)
        except EdgeposError as error:
            run.error = str(error)
            return None


async def run_simulation(
    url: str,
    *,
    vehicles: int = 1,
    scenario_name: str = "rsu-imu",
    admin_key: str | None = None,
    seed: int = 0,
    batch_epochs: int = 20,
    realtime: bool = False,
    epochs: int | None = None,
    progress_stream: TextIO | None = None,
    timeout: float = 30.0,
    keep_sessions: bool = False,
    delivery: LateDelivery | None = None,
    drop_late: bool = False,
) -> SimulationResult:
    """Run the simulation against ``url``; vehicle i's noise is :func:`common.vehicle_rng(seed, i)`.
    ``delivery``: measurements arrive late as it says (vehicle i's delays from child i of
    SeedSequence([seed, 1])); ``drop_late``: those that missed their epoch's batch are dropped."""
    if vehicles < 1:
        raise ValueError("vehicles must be >= 1")
    scenario = common.SCENARIOS[scenario_name]()
    streams = [common.vehicle_epochs(scenario, seed, i)[:epochs] for i in range(vehicles)]
    if delivery is None:
        batches = [common.wire_batches(stream, batch_epochs) for stream in streams]
    else:
        batches = [
            _late_batches(stream, delivery, seed, i, batch_epochs, drop_late)
            for i, stream in enumerate(streams)
        ]
    total = sum(len(stream) for stream in streams)
    runs = [VehicleRun(index=i, vehicle_id=f"sim-{i + 1}") for i in range(vehicles)]
    progress = Progress(total, vehicles, progress_stream)
    limits = httpx.Limits(max_connections=vehicles + 1, max_keepalive_connections=vehicles + 1)
    started = time.perf_counter()
    async with AsyncEdgeposClient(url, admin_key, timeout=timeout, limits=limits) as client:
        await client.put_rsus(common.scenario_rsus(scenario))
        start = common.initial_state(scenario)
        pipeline = common.SCENARIO_PIPELINE[scenario_name]
        sessions = await asyncio.gather(
            *(client.create_session(run.vehicle_id, pipeline, initial_state=start) for run in runs)
        )
        for run, session in zip(runs, sessions):
            run.session_id = session.session_id
        reporter = asyncio.create_task(progress.run())
        try:
            t0 = time.perf_counter()
            pace = scenario.period if realtime else None
            await asyncio.gather(
                *(_drive(client, s, r, b, pace, t0, progress) for s, r, b in zip(sessions, runs, batches))
            )
        finally:
            reporter.cancel()
            progress.show(final=True)
            if not keep_sessions:
                await asyncio.gather(*(client.delete_session(s) for s in sessions), return_exceptions=True)
    for run in runs:
        run.position_rmse, run.velocity_rmse = rmse(run.fixes, scenario)
    epochs_count = len(streams[0]) if streams else 0
    return SimulationResult(
        scenario=scenario.name,
        seed=seed,
        batch_epochs=batch_epochs,
        epochs=epochs_count,
        vehicles=runs,
        elapsed_s=time.perf_counter() - started,
    )


def _rmse(squares: list[float]) -> float | None:
    """Root mean of squared errors; None without any."""
    return math.sqrt(float(np.mean(squares))) if squares else None


def _late_batches(
    epochs: list[list[Observation]],
    delivery: LateDelivery,
    seed: int,
    vehicle: int,
    batch_epochs: int,
    drop_late: bool,
) -> list[list[common.WireMeasurement]]:
    """Vehicle ``vehicle``'s batches as they would reach the server with ``delivery``'s delays."""
    observations = [o for epoch in epochs for o in epoch]
    rng = np.random.default_rng(np.random.SeedSequence([seed, 1], spawn_key=(vehicle,)))
    arrivals = arrival_times(observations, delivery, rng)
    return [
        [common.to_wire(o) for o in batch]
        for batch in arrival_batches(observations, arrivals, batch_epochs, drop_late=drop_late)
    ]


def _format(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def report(result: SimulationResult) -> str:
    """The table of each vehicle's RMSE and the mean."""
    lines = [
        (
            f"scenario {result.scenario}, seed {result.seed}, {result.epochs} epochs per vehicle in batches of "
            f"{result.batch_epochs}, {result.elapsed_s:.1f} s"
        ),
        f"{'vehicle':<12} {'fixes':>6} {'position RMSE (m)':>18} {'velocity RMSE (m/s)':>20}  error",
    ]
    for v in result.vehicles:
        lines.append(
            f"{v.vehicle_id:<12} {len(v.fixes):>6} {_format(v.position_rmse):>18} "
            f"{_format(v.velocity_rmse):>20}  {v.error or ''}"
        )
    lines.append(
        f"{'mean':<12} {'':>6} {_format(result.mean_position_rmse):>18} {_format(result.mean_velocity_rmse):>20}"
    )
    return "\n".join(lines)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", required=True, help="base URL of the server, e.g. http://127.0.0.1:8000")
    parser.add_argument("--vehicles", type=int, default=1, help="simulated vehicles (default 1)")
    parser.add_argument(
        "--scenario",
        choices=sorted([*common.SCENARIOS, *federated_sim.SCENARIOS, *v2v_sim.SCENARIOS]),
        default="rsu-imu",
        help="scenario (v2v: --vehicles groups of the paper's four vehicles)",
    )
    parser.add_argument(
        "--layout",
        choices=("straight", "ring"),
        default="straight",
        help="v2v only: the paper's case (default straight)",
    )
    parser.add_argument(
        "--method",
        choices=("gps", "gps_dr", "ukf", "aug_ukf"),
        default="aug_ukf",
        help="v2v only: the v2v_coop method every vehicle uses (default aug_ukf)",
    )
    parser.add_argument(
        "--admin-key",
        default=None,
        help="admin key: opens the simulated vehicles' sessions and loads the RSU map (default $EDGEPOS_ADMIN_KEY)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="noise seed; vehicle i uses child i of it (default 0)"
    )
    parser.add_argument("--batch-epochs", type=int, default=20, help="epochs per batch (default 20)")
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument(
        "--realtime", dest="realtime", action="store_true", help="pace batches on the scenario's clock"
    )
    pace.add_argument(
        "--fast", dest="realtime", action="store_false", help="send as fast as answered (default)"
    )
    parser.set_defaults(realtime=False)
    parser.add_argument("--epochs", type=int, default=None, help="only the first N epochs of the scenario")
    parser.add_argument(
        "--timeout", type=float, default=30.0, help="seconds per request attempt (default 30)"
    )
    parser.add_argument(
        "--json", type=Path, default=None, metavar="FILE", help="also write the results as JSON"
    )
    add_delivery_arguments(
        parser,
        "rsu-imu: run three times, in order, with a fraction F of the RSU measurements late (see "
        "--max-delay), and with those dropped; report the RMSE of the last fix received per epoch of each",
    )


def run(args: argparse.Namespace) -> int:
    key = common.admin_key(args.admin_key)
    if key is None:
        print(
            "edgepos simulate: opening the simulated vehicles' sessions (and loading the RSU map) needs the admin "
            "key: pass --admin-key or set EDGEPOS_ADMIN_KEY (a server that generated its key printed it and saved "
            "it to edgepos-admin.key)",
            file=sys.stderr,
        )
        return 2
    args.admin_key = key
    if args.json is not None and (problem := prepare_output(args.json)) is not None:
        print(f"edgepos simulate: --json: {problem}", file=sys.stderr)
        return 2
    if args.scenario in federated_sim.SCENARIOS:
        return _run_federated(args)
    if args.scenario in v2v_sim.SCENARIOS:
        return _run_v2v(args)
    if args.vehicles < 1 or args.batch_epochs < 1 or (args.epochs is not None and args.epochs < 1):
        print("edgepos simulate: --vehicles, --batch-epochs and --epochs must be >= 1", file=sys.stderr)
        return 2
    if args.delay_fraction is not None:
        return _run_late(args, key)
    try:
        result = asyncio.run(
            run_simulation(
                args.url,
                vehicles=args.vehicles,
                scenario_name=args.scenario,
                admin_key=key,
                seed=args.seed,
                batch_epochs=args.batch_epochs,
                realtime=args.realtime,
                epochs=args.epochs,
                progress_stream=sys.stderr,
                timeout=args.timeout,
            )
        )
    except EdgeposError as error:
        print(f"edgepos simulate: {error}", file=sys.stderr)
        return 1
    print(report(result))
    if args.json is not None:
        write_output(args.json, json.dumps(result.to_json(), indent=2) + "\n")
    return 1 if any(v.error for v in result.vehicles) else 0


LATE_MODES = (("in order", None, False), ("late", "late", False), ("late dropped", "late", True))


def _run_late(args: argparse.Namespace, key: str) -> int:
    """The same vehicles in order, with late RSU measurements, and with those dropped, one after the other."""
    try:
        delivery = delivery_from(args)
        assert delivery is not None  # only called with --delay-fraction
    except ValueError as error:
        print(f"edgepos simulate: {error}", file=sys.stderr)
        return 2
    results: dict[str, SimulationResult] = {}
    for label, late, drop in LATE_MODES:
        try:
            results[label] = asyncio.run(
                run_simulation(
                    args.url,
                    vehicles=args.vehicles,
                    scenario_name=args.scenario,
                    admin_key=key,
                    seed=args.seed,
                    batch_epochs=args.batch_epochs,
                    realtime=args.realtime,
                    epochs=args.epochs,
                    progress_stream=sys.stderr,
                    timeout=args.timeout,
                    delivery=delivery if late else None,
                    drop_late=drop,
                )
            )
        except EdgeposError as error:
            print(f"edgepos simulate: {label}: {error}", file=sys.stderr)
            return 1
    print(late_report(results, delivery, args.batch_epochs))
    if args.json is not None:
        document = {label: result.to_json() for label, result in results.items()}
        write_output(args.json, json.dumps(document, indent=2) + "\n")
    return 1 if any(v.error for r in results.values() for v in r.vehicles) else 0


def late_report(results: dict[str, SimulationResult], delivery: LateDelivery, batch_epochs: int) -> str:
    """Mean RMSE of the last fix per epoch in each delivery, and its ratio to the in-order run."""
    base = results["in order"].mean_position_rmse
    lines = [
        (
            f"{delivery.fraction:.0%} of the RSU measurements {delivery.min_delay_s:g}-{delivery.max_delay_s:g} s "
            f"late, batches every {batch_epochs} epoch(s); RMSE of the last fix received per epoch, mean over vehicles"
        ),
        (
            f"{'delivery':<14} {'position RMSE (m)':>18} {'x in order':>11} {'velocity RMSE (m/s)':>20}  errors"
            "  waits (429)"
        ),
    ]
    for label, result in results.items():
        position = result.mean_position_rmse
        ratio = "-" if position is None or not base else f"{position / base:.4f}"
        errors = sum(1 for v in result.vehicles if v.error)
        waits = sum(v.rate_limited for v in result.vehicles)
        lines.append(
            f"{label:<14} {_format(position):>18} {ratio:>11} {_format(result.mean_velocity_rmse):>20}  "
            f"{errors:>6}  {waits:>11}"
        )
    return "\n".join(lines)


def _run_federated(args: argparse.Namespace) -> int:
    """--scenario federated: target vehicles with their assisting vehicles, no RSU map."""
    if args.vehicles < 1 or args.batch_epochs < 1 or (args.epochs is not None and args.epochs < 1):
        print("edgepos simulate: --vehicles, --batch-epochs and --epochs must be >= 1", file=sys.stderr)
        return 2
    try:
        targets, elapsed = asyncio.run(
            federated_sim.run_federated(
                args.url,
                vehicles=args.vehicles,
                seed=args.seed,
                batch_epochs=args.batch_epochs,
                realtime=args.realtime,
                epochs=args.epochs,
                timeout=args.timeout,
                admin_key=args.admin_key,
            )
        )
    except EdgeposError as error:
        print(f"edgepos simulate: {error}", file=sys.stderr)
        return 1
    print(federated_sim.report(targets, args.seed, elapsed))
    if args.json is not None:
        document = {
            "scenario": "federated",
            "seed": args.seed,
            "vehicles": [
                {
                    "vehicle_id": v.vehicle_id,
                    "fixes": len(v.fixes),
                    "position_rmse": v.position_rmse,
                    "error": v.error,
                }
                for v in targets
            ],
        }
        write_output(args.json, json.dumps(document, indent=2) + "\n")
    return 1 if any(v.error for v in targets) else 0


def _run_v2v(args: argparse.Namespace) -> int:
    """--scenario v2v: groups of the paper's four vehicles ranging to each other, no RSU map."""
    if args.vehicles < 1 or args.batch_epochs < 1 or (args.epochs is not None and args.epochs < 1):
        print("edgepos simulate: --vehicles, --batch-epochs and --epochs must be >= 1", file=sys.stderr)
        return 2
    try:
        vehicles, elapsed = asyncio.run(
            v2v_sim.run_v2v(
                args.url,
                groups=args.vehicles,
                seed=args.seed,
                layout=args.layout,
                method=args.method,
                batch_epochs=args.batch_epochs,
                realtime=args.realtime,
                epochs=args.epochs,
                timeout=args.timeout,
                admin_key=args.admin_key,
            )
        )
    except EdgeposError as error:
        print(f"edgepos simulate: {error}", file=sys.stderr)
        return 1
    print(v2v_sim.report(vehicles, args.seed, args.layout, args.method, elapsed))
    if args.json is not None:
        document = {
            "scenario": "v2v",
            "layout": args.layout,
            "method": args.method,
            "seed": args.seed,
            "vehicles": [
                {
                    "vehicle_id": v.vehicle_id,
                    "fixes": len(v.fixes),
                    "position_rmse": v.position_rmse,
                    "error": v.error,
                }
                for v in vehicles
            ],
        }
        write_output(args.json, json.dumps(document, indent=2) + "\n")
    return 1 if any(v.error for v in vehicles) else 0
