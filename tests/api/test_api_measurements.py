"""Each wire measurement's ``to_observation``: every field of the observation holds the wire field of its
name (the constructors take them by position, so an order that drifted would show here)."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest
from edgepos.api.measurement_schemas import MEASUREMENT_TYPES, BatchIn

WIRE_NAMES = {"pseudorange": "pseudorange_m", "cn0": "cn0_dbhz"}
"""Observation fields whose wire field has another name."""

# Every field of every type given, each with a value no other field of its measurement has.
MEASUREMENTS: list[dict[str, Any]] = [
    {"type": "rsu", "t": 0.5, "rsu_id": "S+000", "range": 8.875, "bearing": 1.5708},
    {"type": "gyro", "t": 0.5, "yaw_rate": -0.01},
    {"type": "rsu_range", "t": 0.5, "rsu_id": "S+000", "range": 8.0},
    {"type": "gnss_fix", "t": 0.5, "x": 1.0, "y": -2.0, "std": 3.0},
    {"type": "odometer", "t": 0.5, "distance": 3.0},
    {"type": "odometer", "t": 0.5, "speed": 15.0},
    {"type": "v2v_range", "t": 0.5, "peer_vehicle_id": "car-2", "range": 120.0},
    {"type": "v2v_range", "t": 0.5, "peer_vehicle_id": "car-2", "toa": 4.0e-7},
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
    },
    {"type": "riss", "t": 1.0, "wheel_speed": 10.0, "accel_x": 0.1, "accel_y": -0.2, "gyro_z": 0.01},
]


def test_the_examples_cover_every_measurement_type() -> None:
    assert {m["type"] for m in MEASUREMENTS} == set(MEASUREMENT_TYPES)


@pytest.mark.parametrize("wire", MEASUREMENTS, ids=lambda m: m["type"])
def test_every_observation_field_holds_the_wire_field_of_its_name(wire: dict[str, Any]) -> None:
    measurement = BatchIn.model_validate({"seq": 1, "measurements": [wire]}).measurements[0]
    observation = measurement.to_observation()
    assert observation.kind == wire["type"]
    for field in dataclasses.fields(observation):
        expected = getattr(measurement, WIRE_NAMES.get(field.name, field.name))
        if isinstance(expected, list):
            expected = tuple(expected)
        value = getattr(observation, field.name)
        assert type(value) is type(expected) and value == expected, field.name
