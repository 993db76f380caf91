"""Shared helpers of the API tests: the paper scenario's RSUs and measurements on the wire."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np
from edgepos.api.settings import Settings
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.sim.scenarios import Scenario, rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs

ADMIN_KEY = "test-admin-key-5b1f0c9e2d7a4e3f"
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
NO_DOPPLER = {
    "doppler_used": None,
    "doppler_reason": None,
    "correction_applied": None,
    "correction_reason": None,
    "noise_std": None,
    "noise_reason": None,
}
"""The Doppler fields of a measurement use that carried no Doppler (every kind but a pseudorange with one),
and the correction fields, null while the site has no differential corrections, and the noise fields (set
only for a gnss_tight pseudorange used in the update)."""


@functools.lru_cache(maxsize=1)
def scenario() -> Scenario:
    return rsu_imu_paper_scenario()


@functools.lru_cache(maxsize=4)
def epochs(seed: int = 7) -> tuple[tuple[Observation, ...], ...]:
    return tuple(tuple(epoch) for epoch in rsu_imu_epochs(scenario(), np.random.default_rng(seed)))


def make_settings(tmp_path: Path, **overrides: Any) -> Settings:
    """Settings for a test app: a known admin key, and any file it writes inside tmp_path."""
    values: dict[str, Any] = {"admin_key": ADMIN_KEY, "admin_key_file": tmp_path / "admin.key", **overrides}
    return Settings(**values)


def wire(observation: Observation) -> dict[str, Any]:
    if isinstance(observation, RsuObservation):
        return {
            "type": "rsu",
            "t": observation.t,
            "rsu_id": observation.rsu_id,
            "range": observation.range,
            "bearing": observation.bearing,
        }
    assert isinstance(observation, GyroObservation)
    return {"type": "gyro", "t": observation.t, "yaw_rate": observation.yaw_rate}


def batch_observations(first: int, count: int, seed: int = 7) -> list[Observation]:
    """Observations of epochs first .. first+count-1 (0-based) of the scenario."""
    return [o for epoch in epochs(seed)[first : first + count] for o in epoch]


def batch_body(seq: int, first: int, count: int, **extra: Any) -> dict[str, Any]:
    return {"seq": seq, "measurements": [wire(o) for o in batch_observations(first, count)], **extra}


def rsu_payload() -> dict[str, Any]:
    return {
        "rsus": [
            {
                "id": r.id,
                "x": r.x,
                "y": r.y,
                "range_std": r.range_std,
                "bearing_std": r.bearing_std,
                "radius": r.radius,
            }
            for r in scenario().rsus
        ]
    }


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def open_session(client: Any, credential: dict[str, str] = ADMIN, **body: Any) -> tuple[str, dict[str, str]]:
    """Create a session (with the admin key unless another ``credential`` header is given); returns its
    id and its Authorization header. A vehicle has one live session: give distinct vehicle ids."""
    response = client.post("/v1/sessions", json={"vehicle_id": "car-1", **body}, headers=credential)
    assert response.status_code == 201, response.text
    created = response.json()
    return created["session_id"], bearer(created["token"])


def assert_error(response: Any, status: int, code: str) -> dict[str, Any]:
    """The response is the standard error body with this status and code; returns its 'error'."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json")
    body = response.json()
    assert set(body) == {"error"}
    error = body["error"]
    assert set(error) == {"code", "message", "problems"}
    assert error["code"] == code
    assert isinstance(error["message"], str) and error["message"]
    for problem in error["problems"]:
        assert set(problem) == {"index", "field", "reason"}
    return error


EVERY_MEASUREMENT: list[dict[str, Any]] = [
    {"type": "rsu", "t": 0.5, "rsu_id": "S+000", "range": 8.875, "bearing": 1.5708},
    {"type": "gyro", "t": 0.5, "yaw_rate": -0.01},
    {"type": "rsu_range", "t": 0.5, "rsu_id": "S+000", "range": 8.0},
    {"type": "gnss_fix", "t": 0.5, "x": 1.0, "y": -2.0, "std": 3.0},
    {"type": "gnss_fix", "t": 0.5, "x": 1.0, "y": -2.0},
    {"type": "odometer", "t": 0.5, "distance": 3.0},
    {"type": "odometer", "t": 0.5, "speed": 15.0},
    {"type": "v2v_range", "t": 0.5, "peer_vehicle_id": "car-2", "range": 120.0},
    {"type": "v2v_range", "t": 0.5, "peer_vehicle_id": "car-2", "toa": 4.0e-7},
    {"type": "pseudorange", "t": 1.0, "system": "G", "prn": 5, "pseudorange_m": 2.1e7, "cn0_dbhz": 40.0},
    {
        "type": "pseudorange",
        "t": 1.0,
        "system": "E",
        "prn": 12,
        "pseudorange_m": 2.4e7,
        "cn0_dbhz": 35.5,
        "sat_position": [2.0e7, -1.5e7, 0.5e7],
        "sat_clock": 1e-4,
        "doppler_hz": -1200.5,
        "carrier_cycles": 1.26e8,
        "lli": 1,
        "sat_velocity": [-2231.5, 372.25, -1830.75],
        "sat_clock_drift": 1.5e-12,
    },
    {"type": "riss", "t": 1.0, "wheel_speed": 10.0, "accel_x": 0.1, "accel_y": -0.2, "gyro_z": 0.01},
]
"""One wire measurement of every type with every field given (each number one no other field of its
measurement has), and some that leave optional fields out."""
