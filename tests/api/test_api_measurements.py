"""Each wire measurement's ``to_observation``: every field of the observation holds the wire field of its
name (the constructors take them by position, so an order that drifted would show here)."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest
from apihelp import EVERY_MEASUREMENT
from edgepos.api.measurement_schemas import MEASUREMENT_TYPES, BatchIn

WIRE_NAMES = {"pseudorange": "pseudorange_m", "cn0": "cn0_dbhz"}
"""Observation fields whose wire field has another name."""


def test_the_examples_cover_every_measurement_type() -> None:
    assert {m["type"] for m in EVERY_MEASUREMENT} == set(MEASUREMENT_TYPES)


@pytest.mark.parametrize("wire", EVERY_MEASUREMENT, ids=lambda m: m["type"])
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
