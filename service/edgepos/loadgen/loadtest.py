"""``edgepos loadtest``: N simulated vehicles against a server on this machine (loopback only, unless
``--allow-remote`` for a deployment the user owns: the load is real traffic).

Each vehicle opens a session at the paper scenario's start and sends batches of B epochs of its
measurements (one of a few noise streams), so the server's filter does the real work. With rate R
(epochs per second of measurement time) a vehicle's batch k is due at its start + k * B / R s of
wall clock; vehicles' starts are spread over one batch interval. A vehicle never has two batches
in flight (seq order), so a slow answer delays its next batch. At the end of the scenario a
vehicle starts a new trip: it deletes its session and opens a fresh one (those calls are counted
apart from the batches). ``--saturate`` ignores the schedule and sends each batch as soon as the
previous one is answered: the server's capacity rather than its latency at a given load.

``--verify`` reads every session back (with the admin key, so that a session the server no longer
holds is a 404 rather than a refused token) before it is deleted, at the end of a
trip and at the end of the run, also the sessions that saw an error, and checks that the server holds
exactly what the vehicle was told (``loadgen/verify.py``): acknowledged batches found, lost
(acknowledged but not stored, with the window of the run over which they were acknowledged) and
inconsistent counters. A batch that got no answer may or may not be stored. The command fails when
anything was lost, inconsistent or could not be read back.

The load generator runs on the same machine as the server, so it reports its own lateness: how
late each batch left against its schedule, split into waits for the vehicle's previous answer and
the generator's own delays, and how far its event loop lagged a 10 ms timer.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
from edgepos_client import AsyncEdgeposClient, EdgeposError, Session

from edgepos.cli_output import prepare_output, write_output
from edgepos.loadgen import common
from edgepos.loadgen.verify import Held, TripLedger, VerifyTally, judge
from edgepos.sim.scenarios import Scenario, rsu_imu_paper_scenario

#: Distinct measurement noise streams shared round-robin by the vehicles (keeps set-up cheap).
NOISE_STREAMS = 8
#: A batch leaving later than this after its due time counts as late (s).
LATE_THRESHOLD_S = 0.010
#: How many error messages the report keeps as examples.
MAX_ERROR_SAMPLES = 5
#: Period of the event-loop lag probe (s).
LAG_PROBE_S = 0.010
#: --verify: how long a session's read-back is retried through a 503 or a dropped connection (s).
READ_BACK_S = 15.0
READ_BACK_RETRY_S = 0.25


@dataclass(frozen=True)
class LoadConfig:
    """One load test: vehicles x rate (epochs/s) in batches of ``batch`` epochs for ``duration`` s."""

    url: str
    vehicles: int
    rate: float
    batch: int
    duration: float
    admin_key: str | None = None
    saturate: bool = False
    timeout: float = 10.0
    seed: int = 0
    verify: bool = False
    retries: int = 0
    """Further attempts of a request after a 503, a dropped connection or a timeout (the client's
    bounded exponential backoff, same bytes and seq); 0 counts every such answer as an error."""
    allow_remote: bool = False
    """Let ``url`` name a non-loopback host (the user's own deployment); off, only loopback is loaded."""

    def problems(self) -> list[str]:
        found = []
        loopback = common.loopback_problem(self.url, allow_remote=self.allow_remote)
        if loopback is not None:
            found.append(loopback)
        if self.vehicles < 1:
            found.append("--vehicles must be >= 1")
        if not self.rate > 0:
            found.append("--rate must be > 0")
        if self.batch < 1:
            found.append("--batch must be >= 1")
        if not 0 < self.duration <= 3600:
            found.append("--duration must be in (0, 3600] s")
        if not self.timeout > 0:
            found.append("--timeout must be > 0")
        if not 0 <= self.retries <= 10:
            found.append("--retries must be in [0, 10]")
        if not self.admin_key:
            found.append(
                "the admin key is needed to open the simulated vehicles' sessions and load the RSU map: pass "
                "--admin-key or set EDGEPOS_ADMIN_KEY"
            )
        return found

    def remote_warning(self) -> str | None:
        """The warning for a load aimed past this machine (None for a loopback target)."""
        host = urlsplit(self.url).hostname or ""
        if common.is_loopback_host(host):
            return None
        return (
            f"WARNING: {common.REMOTE_FLAG}: sending real load ({self.vehicles} vehicles x {self.rate:g} Hz for "
            f"{self.duration:g} s) to {host}, not this machine; only to a deployment you own or are "
            "authorised to load, and not one that serves real vehicles"
        )

    @property
    def interval_s(self) -> float:
        """Wall-clock seconds between a vehicle's batches."""
        return self.batch / self.rate


@dataclass
class Recorder:
    """What the vehicles observed; only batch requests count in requests, latency and errors."""

    latencies_ms: list[float] = field(default_factory=list)
    epochs: int = 0
    requests: int = 0
    errors: Counter[str] = field(default_factory=Counter)
    error_samples: list[str] = field(default_factory=list)
    lateness_ms: list[float] = field(default_factory=list)
    late_waiting_server: int = 0
    late_generator: int = 0
    unsent: int = 0
    loop_lag_ms: list[float] = field(default_factory=list)
    trips: int = 0
    trip_errors: Counter[str] = field(default_factory=Counter)
    first_send: float | None = None
    last_answer: float | None = None
    verify: VerifyTally = field(default_factory=VerifyTally)
    run_started: float | None = None  # clock time the schedule started (loss window offsets are from it)


@dataclass(frozen=True)
class LoadReport:
    config: LoadConfig
    elapsed_s: float
    recorder: Recorder

    @property
    def errors(self) -> int:
        return sum(self.recorder.errors.values())

    @property
    def epochs_per_s(self) -> float:
        return self.recorder.epochs / self.elapsed_s if self.elapsed_s > 0 else 0.0

    @property
    def requests_per_s(self) -> float:
        return self.recorder.requests / self.elapsed_s if self.elapsed_s > 0 else 0.0

    def latency(self, q: float) -> float | None:
        return common.percentile(self.recorder.latencies_ms, q)

    def to_json(self) -> dict[str, Any]:
        r, c = self.recorder, self.config
        return {
            "epochs_per_s": self.epochs_per_s,
            "requests_per_s": self.requests_per_s,
            "requests": r.requests,
            "errors": self.errors,
            "latency_ms": {"p50": self.latency(50), "p95": self.latency(95), "p99": self.latency(99)},
            "latency_max_ms": max(r.latencies_ms) if r.latencies_ms else None,
            "epochs": r.epochs,
            "elapsed_s": self.elapsed_s,
            "errors_by_code": dict(r.errors),
            "error_samples": list(r.error_samples),
            "config": {
                "vehicles": c.vehicles,
                "rate_hz": c.rate,
                "batch_epochs": c.batch,
                "duration_s": c.duration,
                "saturate": c.saturate,
                "offered_epochs_per_s": None if c.saturate else c.vehicles * c.rate,
            },
            "lateness": {
                "late_batches": r.late_waiting_server + r.late_generator,
                "late_waiting_for_server": r.late_waiting_server,
                "late_generator": r.late_generator,
                "unsent_batches": r.unsent,
                "threshold_ms": LATE_THRESHOLD_S * 1e3,
                "p99_ms": common.percentile(r.lateness_ms, 99),
                "max_ms": max(r.lateness_ms) if r.lateness_ms else None,
                "loop_lag_p99_ms": common.percentile(r.loop_lag_ms, 99),
                "loop_lag_max_ms": max(r.loop_lag_ms) if r.loop_lag_ms else None,
            },
            "trips": {"started": r.trips, "errors_by_code": dict(r.trip_errors)},
            "verify": _verify_json(r) if c.verify else None,
        }


def _verify_json(recorder: Recorder) -> dict[str, Any]:
    tally, origin = recorder.verify, recorder.run_started
    window = tally.loss_window_s()
    return {
        "sessions_checked": tally.sessions,
        "acknowledged_batches": tally.acknowledged,
        "found": tally.found,
        "lost": tally.lost,
        "loss_window_s": window,
        "loss_started_s": (
            None if tally.lost_from is None or origin is None else round(tally.lost_from - origin, 6)
        ),
        "sessions_gone": tally.sessions_gone,
        "unreadable": tally.unreadable,
        "mismatches": tally.inconsistent,
        "samples": list(tally.samples),
    }


def _noise_batches(scenario: Scenario, config: LoadConfig) -> list[list[list[common.WireMeasurement]]]:
    streams = min(NOISE_STREAMS, config.vehicles)
    return [
        common.wire_batches(common.vehicle_epochs(scenario, config.seed, index), config.batch)
        for index in range(streams)
    ]


class WallClock:
    """The clock vehicles keep their schedule by; tests substitute a virtual one to stay deterministic."""

    @staticmethod
    def now() -> float:
        return time.perf_counter()

    @staticmethod
    async def sleep(seconds: float) -> None:
        await asyncio.sleep(seconds)


WALL_CLOCK = WallClock()
"""The clock of every vehicle unless a test gives its own."""


def batches_due(duration: float, offset: float, interval: float) -> int:
    """How many batches fall due in [offset, duration): batch k is due at offset + k * interval.

    Counted from the index, not by adding intervals up, so that a due time landing on the end
    (0.5 s / 0.02 s) is not miscounted by accumulated rounding.
    """
    span = (duration - offset) / interval
    return max(0, math.ceil(span - 1e-9 * max(1.0, span)))


class Vehicle:
    """One simulated vehicle: sends its batches on schedule, starting a new trip at the scenario's end."""

    def __init__(
        self,
        index: int,
        client: AsyncEdgeposClient,
        batches: list[list[common.WireMeasurement]],
        scenario: Scenario,
        recorder: Recorder,
        verify: bool = False,
        clock: WallClock | None = None,
    ) -> None:
        self.vehicle_id = f"load-{index + 1}"
        self.clock = clock or WALL_CLOCK
        self.client = client
        self.batches = batches
        self.start_state = common.initial_state(scenario)
        self.recorder = recorder
        self.session: Session | None = None
        self.position = 0
        self.verify = verify
        self.ledger = TripLedger()

    async def check_session(self) -> None:
        """--verify: read the session back (through a recovering server: a 503 or a dropped connection
        is retried for up to READ_BACK_S) and judge it against what the vehicle was told."""
        if self.session is None:
            return
        tally = self.recorder.verify
        name = f"{self.vehicle_id} session {self.session.session_id}"
        deadline = self.clock.now() + READ_BACK_S
        while True:
            try:
                info = await self.client.get_session(
                    self.session.session_id
                )  # a bare id: read with the admin key
            except EdgeposError as error:
                if error.status == 404:
                    tally.add(name, self.ledger, judge(self.ledger, None), True, MAX_ERROR_SAMPLES)
                    return
                passing = error.status is None or error.status in (429, 503)
                if passing and self.clock.now() < deadline:
                    await self.clock.sleep(READ_BACK_RETRY_S)
                    continue
                tally.add_unreadable(name, self.ledger, str(error), MAX_ERROR_SAMPLES)
                return
            held = Held(info.last_seq, info.batches, info.epochs)
            tally.add(name, self.ledger, judge(self.ledger, held), False, MAX_ERROR_SAMPLES)
            return

    async def new_trip(self) -> None:
        """Close the current session (if any) and open a fresh one at the scenario's start."""
        recorder = self.recorder
        if self.session is not None:
            if self.verify:
                await self.check_session()
            try:
                await self.client.delete_session(self.session)
            except EdgeposError as error:
                recorder.trip_errors[error.code] += 1
            self.session = None
        self.session = await self.client.create_session(self.vehicle_id, initial_state=self.start_state)
        self.position = 0
        self.ledger = TripLedger()
        recorder.trips += 1

    async def send_one(self) -> None:
        """Send the next batch; an error is recorded and the vehicle restarts its trip."""
        recorder = self.recorder
        if self.session is None or self.position >= len(self.batches):
            await self.new_trip()
        assert self.session is not None
        batch = self.batches[self.position]
        started = self.clock.now()
        if recorder.first_send is None:
            recorder.first_send = started
        try:
            fixes = await self.client.send_batch(self.session, batch)
        except EdgeposError as error:
            recorder.requests += 1
            recorder.errors[error.code] += 1
            if len(recorder.error_samples) < MAX_ERROR_SAMPLES:
                recorder.error_samples.append(str(error))
            if (
                error.status is None or error.status >= 500
            ):  # no answer, or one after a failure: maybe applied
                self.ledger.unanswered(len({measurement.t for measurement in batch}))
            self.position = len(self.batches)  # resynchronise: the next batch ends this trip, opens a new one
            return
        finished = self.clock.now()
        recorder.requests += 1
        recorder.latencies_ms.append((finished - started) * 1e3)
        recorder.epochs += len(fixes)
        recorder.last_answer = finished
        self.position += 1
        self.ledger.acknowledge(finished, len(fixes))

    async def run(self, config: LoadConfig, start: float, offset: float) -> None:
        """Send until ``config.duration`` s after ``start``; batch k is due at start + offset + k * interval.

        Open loop: a batch due while the previous one is still unanswered leaves late; what is
        still due when the run ends is counted as unsent, so every due batch is sent or counted.
        """
        clock = self.clock
        end = start + config.duration
        due_count = batches_due(config.duration, offset, config.interval_s)
        answered = start
        recorder = self.recorder
        k = 0
        while True:
            if config.saturate:
                if clock.now() >= end:
                    return
            else:
                if k >= due_count:
                    return
                if clock.now() >= end:  # behind schedule when the test ends: it stays bounded
                    recorder.unsent += due_count - k
                    return
                due = start + offset + k * config.interval_s
                delay = due - clock.now()
                if delay > 0:
                    await clock.sleep(delay)
                lateness = clock.now() - due
                recorder.lateness_ms.append(max(0.0, lateness) * 1e3)
                if lateness > LATE_THRESHOLD_S:
                    if answered > due:
                        recorder.late_waiting_server += 1
                    else:
                        recorder.late_generator += 1
                k += 1
            try:
                await self.send_one()
            except EdgeposError as error:  # opening a trip failed: count it, keep going
                recorder.trip_errors[error.code] += 1
                self.session = None
            answered = clock.now()


async def _probe_loop_lag(recorder: Recorder) -> None:
    loop = asyncio.get_running_loop()
    while True:
        planned = loop.time() + LAG_PROBE_S
        await asyncio.sleep(LAG_PROBE_S)
        recorder.loop_lag_ms.append(max(0.0, loop.time() - planned) * 1e3)


async def _ensure_rsus(client: AsyncEdgeposClient, scenario: Scenario) -> None:
    """Load the scenario's RSU map (admin key)."""
    await client.put_rsus(common.scenario_rsus(scenario))


async def run_load(config: LoadConfig) -> LoadReport:
    """Run ``config`` and return what was measured. Raises ValueError for a refused config."""
    problems = config.problems()
    if problems:
        raise ValueError("; ".join(problems))
    scenario = rsu_imu_paper_scenario()
    batches = _noise_batches(scenario, config)
    recorder = Recorder()
    # One client (one keep-alive connection) per vehicle, as vehicles have: a shared pool of N
    # connections costs O(N) per request in httpcore's bookkeeping, which made the generator, not the
    # server, the bottleneck at 1,000 vehicles.
    own_connection = httpx.Limits(max_connections=1, max_keepalive_connections=1)
    async with contextlib.AsyncExitStack() as stack:
        admin = await stack.enter_async_context(
            AsyncEdgeposClient(config.url, config.admin_key, timeout=config.timeout, retries=config.retries)
        )
        await _ensure_rsus(
            admin, scenario
        )  # a 503 while the service warms up is retried as the vehicles retry
        vehicles = []
        for i in range(config.vehicles):
            client = await stack.enter_async_context(
                AsyncEdgeposClient(
                    config.url,
                    config.admin_key,
                    timeout=config.timeout,
                    retries=config.retries,
                    limits=own_connection,
                )
            )
            vehicles.append(Vehicle(i, client, batches[i % len(batches)], scenario, recorder, config.verify))
        await asyncio.gather(*(vehicle.new_trip() for vehicle in vehicles))
        recorder.trips = 0  # count trips started after the first
        probe = asyncio.create_task(_probe_loop_lag(recorder))
        start = time.perf_counter()
        recorder.run_started = start
        try:
            spread = 0.0 if config.saturate else config.interval_s
            await asyncio.gather(
                *(
                    vehicle.run(config, start, spread * i / config.vehicles)
                    for i, vehicle in enumerate(vehicles)
                )
            )
        finally:
            probe.cancel()
        finished = time.perf_counter()
        if config.verify:
            await asyncio.gather(*(vehicle.check_session() for vehicle in vehicles))
        await asyncio.gather(
            *(v.client.delete_session(v.session) for v in vehicles if v.session is not None),
            return_exceptions=True,
        )
    elapsed = max(config.duration, finished - start) if not config.saturate else finished - start
    return LoadReport(config=config, elapsed_s=elapsed, recorder=recorder)


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f} ms"


def summary(report: LoadReport) -> str:
    """The human-readable result."""
    data = report.to_json()
    c, late = data["config"], data["lateness"]
    mode = (
        "saturating (closed loop)" if c["saturate"] else f"offered {c['offered_epochs_per_s']:.0f} epochs/s"
    )
    lines = [
        (
            f"loadtest {report.config.url}: {c['vehicles']} vehicles x {c['rate_hz']:g} Hz, "
            f"batches of {c['batch_epochs']} epochs, {c['duration_s']:g} s, {mode}"
        ),
        f"  epochs/s        {data['epochs_per_s']:.1f}  ({data['epochs']} epochs in {data['elapsed_s']:.1f} s)",
        f"  requests/s      {data['requests_per_s']:.1f}  ({data['requests']} batch requests)",
        (
            f"  latency         p50 {_ms(data['latency_ms']['p50'])}, p95 {_ms(data['latency_ms']['p95'])}, "
            f"p99 {_ms(data['latency_ms']['p99'])}, max {_ms(data['latency_max_ms'])}"
        ),
        f"  errors          {data['errors']}" + (f" {data['errors_by_code']}" if data["errors"] else ""),
        *(f"    e.g. {sample}" for sample in data["error_samples"]),
        f"  trips restarted {data['trips']['started']} (vehicles that reached the scenario's end and reopened "
        "a session)"
        + (f", trip errors {data['trips']['errors_by_code']}" if data["trips"]["errors_by_code"] else ""),
    ]
    if not c["saturate"]:
        lines.append(
            f"  lateness        {late['late_batches']} batch(es) left > {late['threshold_ms']:.0f} ms late "
            f"({late['late_waiting_for_server']} waiting for the previous answer, {late['late_generator']} "
            f"generator); p99 {_ms(late['p99_ms'])}, max {_ms(late['max_ms'])}"
        )
        if late["unsent_batches"]:
            offered = round(c["vehicles"] * c["duration_s"] * c["rate_hz"] / c["batch_epochs"])
            lines.append(
                f"  behind schedule {late['unsent_batches']} of {offered} due batch(es) not sent by the end: "
                "the server (or the generator) could not keep up with the offered load"
            )
    verify = data["verify"]
    if verify is not None:
        lost = f"{verify['lost']} lost"
        if verify["lost"] and verify["loss_started_s"] is not None:
            lost += (
                f" (acknowledged over {verify['loss_window_s']:.2f} s from {verify['loss_started_s']:.2f} s into "
                f"the run; {verify['sessions_gone']} session(s) gone)"
            )
        lines.append(
            f"  verify          {verify['sessions_checked']} session(s) read back: "
            f"{verify['acknowledged_batches']} acknowledged batch(es), {verify['found']} found, {lost}, "
            f"{verify['mismatches']} inconsistent, {verify['unreadable']} unreadable"
        )
        lines.extend(f"    e.g. {sample}" for sample in verify["samples"])
    lines.append(
        f"  generator loop  lag p99 {_ms(late['loop_lag_p99_ms'])}, max {_ms(late['loop_lag_max_ms'])} "
        "(the load generator shares this machine's cores with the server)"
    )
    return "\n".join(lines)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = (
        "Output: 'trips restarted' counts the vehicles that reached the end of the scenario and started "
        "over (deleted their session and opened a fresh one); those calls are counted apart from the batches."
    )
    parser.add_argument(
        "--url",
        required=True,
        help=f"server base URL; loopback hosts only (127.0.0.0/8, localhost, ::1) unless {common.REMOTE_FLAG}",
    )
    parser.add_argument(
        common.REMOTE_FLAG,
        action="store_true",
        help="allow a --url on another machine: only for a deployment you own or are authorised to load "
        "(the load is real traffic; a warning is printed)",
    )
    parser.add_argument("--vehicles", type=int, required=True, help="concurrent simulated vehicles")
    parser.add_argument(
        "--rate", type=float, required=True, help="epochs per second of measurement time per vehicle (Hz)"
    )
    parser.add_argument(
        "--batch", type=int, required=True, help="epochs per batch (a batch every BATCH/RATE s)"
    )
    parser.add_argument("--duration", type=float, required=True, help="seconds to run (at most 3600)")
    parser.add_argument("--json", type=Path, default=None, metavar="FILE", help="write the figures as JSON")
    parser.add_argument(
        "--admin-key",
        default=None,
        help="admin key: opens the vehicles' sessions and loads the RSU map (default $EDGEPOS_ADMIN_KEY)",
    )
    parser.add_argument(
        "--saturate",
        action="store_true",
        help="closed loop: send each batch as soon as the previous is answered",
    )
    parser.add_argument(
        "--timeout", type=float, default=10.0, help="seconds per attempt of a request (default 10)"
    )
    parser.add_argument(
        "--retries",
        type=int,
        default=0,
        help="further attempts after a 503, a dropped connection or a timeout, with exponential backoff from "
        "0.2 s (default 0: every such answer counts as an error)",
    )
    parser.add_argument("--seed", type=int, default=0, help="measurement noise seed (default 0)")
    parser.add_argument(
        "--verify",
        action="store_true",
        help="read every session back before deleting it (also those that saw an error) and count the "
        "acknowledged batches found and lost and any counters that disagree (exit status 1 if any batch was "
        "lost, any session disagrees or could not be read back)",
    )


def run(args: argparse.Namespace) -> int:
    config = LoadConfig(
        url=args.url,
        vehicles=args.vehicles,
        rate=args.rate,
        batch=args.batch,
        duration=args.duration,
        admin_key=common.admin_key(args.admin_key),
        saturate=args.saturate,
        timeout=args.timeout,
        seed=args.seed,
        verify=args.verify,
        retries=args.retries,
        allow_remote=args.allow_remote,
    )
    problems = config.problems()
    if not problems and args.json is not None and (problem := prepare_output(args.json)) is not None:
        problems.append(f"--json: {problem}")
    if problems:
        for problem in problems:
            print(f"edgepos loadtest: {problem}", file=sys.stderr)
        return 2
    warning = config.remote_warning()
    if warning is not None:
        print(f"edgepos loadtest: {warning}", file=sys.stderr)
    try:
        report = asyncio.run(run_load(config))
    except EdgeposError as error:
        print(f"edgepos loadtest: {error}", file=sys.stderr)
        return 1
    print(summary(report))
    if args.json is not None:
        write_output(args.json, json.dumps(report.to_json(), indent=2) + "\n")
    return 1 if config.verify and report.recorder.verify.failed else 0
