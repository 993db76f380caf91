"""``edgepos simulate --scenario v2v``: the V2V cooperative paper's vehicles through a server.

Group g is run g of the scenario (``edgepos.sim.v2v.make_run(seed, g, layout)``, the draws
``edgepos eval v2v --seed S`` uses). Each of its four vehicles has its own ``v2v_coop`` session and
its own HTTP client; they range to each other by vehicle id, and the server reads each one's
neighbours from their sessions. Batches go out epoch group by epoch group with all vehicles of all
groups concurrently, so a vehicle may see a neighbour's estimate of the same step or of the step
before, depending on which request the server answered first: the figures agree with the
in-process evaluation within Monte Carlo noise, not bit for bit.
"""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass, field

import httpx
from edgepos_client import AsyncEdgeposClient, EdgeposError, Fix, Session

from edgepos.loadgen import common
from edgepos.sim.v2v import PAPER_OPTIONS, STEP, VEHICLE_IDS, make_run

SCENARIOS = ("v2v",)


@dataclass
class V2vVehicle:
    """One simulated vehicle: its group (run), index in the group, fixes back and position RMSE."""

    group: int
    index: int
    vehicle_id: str
    position_rmse: float | None = None
    fixes: list[Fix] = field(default_factory=list)
    error: str | None = None


async def run_v2v(
    url: str,
    *,
    groups: int = 1,
    seed: int = 1,
    layout: str = "straight",
    method: str = "aug_ukf",
    batch_epochs: int = 1,
    realtime: bool = False,
    epochs: int | None = None,
    timeout: float = 30.0,
    admin_key: str | None = None,
) -> tuple[list[V2vVehicle], float]:
    """Drive ``groups`` x 4 vehicles through ``url``; each vehicle's position RMSE over epochs 1.."""
    runs = [make_run(seed, g, layout) for g in range(groups)]
    count = len(runs[0].times) if epochs is None else min(epochs, len(runs[0].times))
    vehicles = [
        V2vVehicle(g, i, f"v2v{seed}-{g + 1}-{vid}")
        for g in range(groups)
        for i, vid in enumerate(VEHICLE_IDS)
    ]
    started = time.perf_counter()
    limits = httpx.Limits(max_connections=1, max_keepalive_connections=1)
    clients: list[AsyncEdgeposClient] = []
    lanes: list[tuple[V2vVehicle, AsyncEdgeposClient, Session]] = []
    try:
        for vehicle in vehicles:
            client = AsyncEdgeposClient(url, admin_key, timeout=timeout, limits=limits)
            clients.append(client)
            session = await client.create_session(
                vehicle.vehicle_id, "v2v_coop", options={"method": method, **PAPER_OPTIONS}
            )
            lanes.append((vehicle, client, session))
        t0 = time.perf_counter()
        for start in range(0, count, batch_epochs):
            stop = min(start + batch_epochs, count)
            if realtime:
                await asyncio.sleep(max(0.0, t0 + stop * STEP - time.perf_counter()))
            await asyncio.gather(
                *(
                    _send(
                        client,
                        session,
                        vehicle,
                        [
                            common.to_wire(o, f"v2v{seed}-{vehicle.group + 1}-")
                            for k in range(start, stop)
                            for o in runs[vehicle.group].observations[vehicle.index][k]
                        ],
                    )
                    for vehicle, client, session in lanes
                )
            )
    finally:
        await asyncio.gather(*(c.delete_session(s) for _, c, s in lanes), return_exceptions=True)
        await asyncio.gather(*(c.close() for c in clients), return_exceptions=True)
    for vehicle in vehicles:
        truth = runs[vehicle.group].positions[vehicle.index]
        errors = [
            (f.x - truth[k, 0]) ** 2 + (f.y - truth[k, 1]) ** 2
            for k, f in enumerate(vehicle.fixes)
            if k >= 1 and f.x is not None
        ]
        vehicle.position_rmse = math.sqrt(sum(errors) / len(errors)) if errors else None
    return vehicles, time.perf_counter() - started


async def _send(
    client: AsyncEdgeposClient, session: Session, vehicle: V2vVehicle, batch: list[common.WireMeasurement]
) -> None:
    if vehicle.error is not None:
        return
    try:
        vehicle.fixes.extend(await client.send_batch(session, batch))
    except EdgeposError as error:
        vehicle.error = str(error)


def report(vehicles: list[V2vVehicle], seed: int, layout: str, method: str, elapsed: float) -> str:
    lines = [
        f"scenario v2v ({layout}, method {method}), seed {seed}, {len(vehicles)} vehicles, {elapsed:.1f} s",
        f"{'vehicle':<22} {'fixes':>6} {'position RMSE (m)':>18}  error",
    ]
    for v in vehicles:
        rmse = "-" if v.position_rmse is None else f"{v.position_rmse:.3f}"
        lines.append(f"{v.vehicle_id:<22} {len(v.fixes):>6} {rmse:>18}  {v.error or ''}")
    values = [v.position_rmse for v in vehicles if v.position_rmse is not None]
    if values:
        lines.append(f"{'all':<22} {'':>6} {math.sqrt(sum(r * r for r in values) / len(values)):>18.3f}")
    return "\n".join(lines)
