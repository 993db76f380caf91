"""``edgepos simulate --scenario federated``: the V2X federated paper's scenario through a server.

Target vehicle i is run i of the scenario (``edgepos.sim.federated.make_run(seed, i, "clean")``,
the same draws ``edgepos eval federated --seed S`` uses). Each target comes with its four assisting
vehicles; every vehicle has its own ``v2x_federated`` session and its own HTTP client. An assisting
vehicle sends its own GNSS fixes (1 m 1-sigma), so the server publishes its track; the target sends its GNSS fixes, gyro, odometer and
V2V ranges to its assisting vehicles, whose positions the server reads from their sessions.
Batches go out epoch group by epoch group, all vehicles concurrently, assisting vehicles' batch of
a group before the target's (the target ranges to where they are, not where they will be); with
``realtime`` each group waits for its last epoch on the scenario's clock.

The in-process evaluation runs the same sessions and publishes with the same function, so the two
see the same neighbour positions when every assisting batch lands before the target's.
"""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass, field

import httpx
from edgepos_client import AsyncEdgeposClient, EdgeposError, Fix, GnssFixMeasurement, Session

from edgepos.loadgen import common
from edgepos.sim.federated import PAPER_OPTIONS, STEP, FederatedRun, make_run

SCENARIOS = ("federated",)


@dataclass
class FederatedVehicle:
    """One target vehicle: its run, the fixes it got back and its position RMSE (epochs 1..)."""

    index: int
    vehicle_id: str
    position_rmse: float | None = None
    fixes: list[Fix] = field(default_factory=list)
    error: str | None = None


def _assist_batches(
    run: FederatedRun, name: str, epochs: int, batch_epochs: int
) -> list[list[common.WireMeasurement]]:
    out: list[list[common.WireMeasurement]] = []
    for start in range(0, epochs, batch_epochs):
        batch: list[common.WireMeasurement] = []
        for k in range(start, min(start + batch_epochs, epochs)):
            fix = run.neighbour_fixes[k][name]
            batch.append(GnssFixMeasurement(t=fix.t, x=fix.x, y=fix.y, std=fix.std))
        out.append(batch)
    return out


async def run_federated(
    url: str,
    *,
    vehicles: int = 1,
    seed: int = 1,
    batch_epochs: int = 5,
    realtime: bool = False,
    epochs: int | None = None,
    timeout: float = 30.0,
    admin_key: str | None = None,
) -> tuple[list[FederatedVehicle], float]:
    """Drive ``vehicles`` targets (and their assisting vehicles) through ``url``; per-target RMSE."""
    runs = [make_run(seed, i, "clean") for i in range(vehicles)]
    count = len(runs[0].times) if epochs is None else min(epochs, len(runs[0].times))
    targets = [FederatedVehicle(i, f"fed{seed}-{i + 1}") for i in range(vehicles)]
    started = time.perf_counter()
    limits = httpx.Limits(max_connections=2, max_keepalive_connections=2)
    clients: list[AsyncEdgeposClient] = []
    sessions = []
    try:
        # (target or None for an assisting vehicle, client, session, batches), assisting vehicles before their target
        lanes: list[
            tuple[FederatedVehicle | None, AsyncEdgeposClient, Session, list[list[common.WireMeasurement]]]
        ] = []
        for target, run in zip(targets, runs):
            prefix = f"{target.vehicle_id}-"
            for name in run.neighbour_ids:
                client = AsyncEdgeposClient(url, admin_key, timeout=timeout, limits=limits)
                clients.append(client)
                session = await client.create_session(prefix + name, "v2x_federated", options=PAPER_OPTIONS)
                sessions.append((client, session))
                lanes.append((None, client, session, _assist_batches(run, name, count, batch_epochs)))
            client = AsyncEdgeposClient(url, admin_key, timeout=timeout, limits=limits)
            clients.append(client)
            session = await client.create_session(target.vehicle_id, "v2x_federated", options=PAPER_OPTIONS)
            sessions.append((client, session))
            batches = [
                [
                    common.to_wire(o, prefix)
                    for k in range(s, min(s + batch_epochs, count))
                    for o in run.observations[k]
                ]
                for s in range(0, count, batch_epochs)
            ]
            lanes.append((target, client, session, batches))
        t0 = time.perf_counter()
        for group, start in enumerate(range(0, count, batch_epochs)):
            if realtime:
                due = t0 + min(start + batch_epochs, count) * STEP
                await asyncio.sleep(max(0.0, due - time.perf_counter()))
            await asyncio.gather(
                *(_send(client, session, b[group], None) for tgt, client, session, b in lanes if tgt is None)
            )
            await asyncio.gather(
                *(
                    _send(client, session, b[group], tgt)
                    for tgt, client, session, b in lanes
                    if tgt is not None
                )
            )
    finally:
        await asyncio.gather(*(c.delete_session(s) for c, s in sessions), return_exceptions=True)
        await asyncio.gather(*(c.close() for c in clients), return_exceptions=True)
    for target, run in zip(targets, runs):
        errors = [
            (f.x - run.truth[k, 0]) ** 2 + (f.y - run.truth[k, 3]) ** 2
            for k, f in enumerate(target.fixes)
            if k >= 1 and f.x is not None
        ]
        target.position_rmse = math.sqrt(sum(errors) / len(errors)) if errors else None
    return targets, time.perf_counter() - started


async def _send(
    client: AsyncEdgeposClient,
    session: Session,
    batch: list[common.WireMeasurement],
    target: FederatedVehicle | None,
) -> None:
    if target is not None and target.error is not None:
        return
    try:
        fixes = await client.send_batch(session, batch)
    except EdgeposError as error:
        if target is not None:
            target.error = str(error)
        raise
    if target is not None:
        target.fixes.extend(fixes)


def report(targets: list[FederatedVehicle], seed: int, elapsed: float) -> str:
    lines = [
        f"scenario federated (clean), seed {seed}, {len(targets)} target vehicles + 4 assisting each, {elapsed:.1f} s",
        f"{'vehicle':<12} {'fixes':>6} {'position RMSE (m)':>18}  error",
    ]
    for v in targets:
        rmse = "-" if v.position_rmse is None else f"{v.position_rmse:.3f}"
        lines.append(f"{v.vehicle_id:<12} {len(v.fixes):>6} {rmse:>18}  {v.error or ''}")
    values = [v.position_rmse for v in targets if v.position_rmse is not None]
    if values:
        lines.append(f"{'mean':<12} {'':>6} {math.sqrt(sum(r * r for r in values) / len(values)):>18.3f}")
    return "\n".join(lines)
