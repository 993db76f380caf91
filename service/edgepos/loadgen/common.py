"""What ``edgepos simulate`` and ``edgepos loadtest`` share: the scenario on the wire (RSU map,
initial state, measurements as client models), per-vehicle noise seeds, the admin key, and the
loopback check."""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Sequence
from urllib.parse import urlsplit

import numpy as np
from edgepos_client import (
    GnssFixMeasurement,
    GyroMeasurement,
    InitialState,
    OdometerMeasurement,
    Rsu,
    RsuMeasurement,
    V2vRangeMeasurement,
)

from edgepos.core.observations import (
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    RsuObservation,
    V2vRangeObservation,
)
from edgepos.sim.scenarios import Scenario, rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs

#: Scenarios by their command-line name.
SCENARIOS = {"rsu-imu": rsu_imu_paper_scenario}
#: Pipeline each scenario is filtered with.
SCENARIO_PIPELINE = {"rsu-imu": "rsu_imu"}
#: 1-sigma of the initial state handed to each session (m, m/s).
INITIAL_POSITION_STD = 1.0
INITIAL_VELOCITY_STD = 1.0

WireMeasurement = (
    RsuMeasurement | GyroMeasurement | GnssFixMeasurement | OdometerMeasurement | V2vRangeMeasurement
)


def scenario_rsus(scenario: Scenario) -> list[Rsu]:
    """The scenario's RSU map as the client sends it."""
    return [
        Rsu(id=r.id, x=r.x, y=r.y, range_std=r.range_std, bearing_std=r.bearing_std, radius=r.radius)
        for r in scenario.rsus
    ]


def initial_state(scenario: Scenario) -> InitialState:
    """The truth at t = 0 (scenario.initial_state is [xp, xv, xa, yp, yv, ya, phi, omega])."""
    xp, xv, _xa, yp, yv, _ya, _phi, _omega = scenario.initial_state
    return InitialState(
        x=xp, y=yp, vx=xv, vy=yv, position_std=INITIAL_POSITION_STD, velocity_std=INITIAL_VELOCITY_STD
    )


def vehicle_rng(seed: int, vehicle: int) -> np.random.Generator:
    """Vehicle ``vehicle``'s (0-based) own noise stream: child ``vehicle`` of SeedSequence(seed)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(vehicle,)))


def vehicle_epochs(scenario: Scenario, seed: int, vehicle: int) -> list[list[Observation]]:
    """The scenario's observations as vehicle ``vehicle`` measures them."""
    return rsu_imu_epochs(scenario, vehicle_rng(seed, vehicle))


def to_wire(observation: Observation, peer_prefix: str = "") -> WireMeasurement:
    """An observation as the client's measurement model (floats copied unchanged); ``peer_prefix``
    goes before a V2V range's peer id, so that simulated fleets of several runs keep apart."""
    if isinstance(observation, GnssFixObservation):
        return GnssFixMeasurement(t=observation.t, x=observation.x, y=observation.y, std=observation.std)
    if isinstance(observation, OdometerObservation):
        return OdometerMeasurement(t=observation.t, distance=observation.distance, speed=observation.speed)
    if isinstance(observation, V2vRangeObservation):
        return V2vRangeMeasurement(
            t=observation.t,
            peer_vehicle_id=f"{peer_prefix}{observation.peer_vehicle_id}",
            range=observation.range,
            toa=observation.toa,
        )
    if isinstance(observation, RsuObservation):
        return RsuMeasurement(
            t=observation.t, rsu_id=observation.rsu_id, range=observation.range, bearing=observation.bearing
        )
    if isinstance(observation, GyroObservation):
        return GyroMeasurement(t=observation.t, yaw_rate=observation.yaw_rate)
    raise TypeError(f"no wire form for {type(observation).__name__}")


def wire_batches(epochs: Sequence[Sequence[Observation]], batch_epochs: int) -> list[list[WireMeasurement]]:
    """Consecutive groups of ``batch_epochs`` epochs (the last may be shorter), flattened to wire."""
    if batch_epochs < 1:
        raise ValueError("batch_epochs must be >= 1")
    return [
        [to_wire(observation) for epoch in epochs[start : start + batch_epochs] for observation in epoch]
        for start in range(0, len(epochs), batch_epochs)
    ]


def admin_key(given: str | None) -> str | None:
    """--admin-key, else $EDGEPOS_ADMIN_KEY, else None."""
    return given or os.environ.get("EDGEPOS_ADMIN_KEY") or None


REMOTE_FLAG = "--allow-remote"
"""The loadtest option that lifts the loopback guard, for a deployment the user owns."""


def loopback_problem(url: str, *, allow_remote: bool = False) -> str | None:
    """Why ``url`` may not be load-tested (None if it is http(s) on a loopback host, or on any host
    with ``allow_remote``: the user's word that the deployment is theirs to load)."""
    try:
        parts = urlsplit(url)
        host = parts.hostname
        _ = parts.port  # raises on a malformed port
    except ValueError as error:
        return f"cannot parse URL {url!r}: {error}"
    if parts.scheme not in ("http", "https"):
        return f"URL {url!r} must start with http:// or https://"
    if not host:
        return f"URL {url!r} names no host"
    if allow_remote or is_loopback_host(host):
        return None
    return (
        f"host {host!r} is not loopback: only localhost, 127.0.0.0/8 and ::1 may be targeted (for a "
        f"deployment you own elsewhere, pass {REMOTE_FLAG})"
    )


def is_loopback_host(host: str) -> bool:
    """``localhost`` or a loopback address (a name other than localhost is never taken as loopback)."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def percentile(values: Sequence[float], q: float) -> float | None:
    """The q-th percentile (linear interpolation), None for no values."""
    if not values:
        return None
    return float(np.percentile(np.asarray(values, dtype=float), q))
