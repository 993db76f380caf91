"""The cooperative measurement types on the wire: their bounds, the 'exactly one of' rules named by
field, and a pipeline that does not use them refusing them with a 4xx that leaves the session as it was."""

from __future__ import annotations

from typing import Any

import pytest
from apihelp import assert_error, batch_body, open_session

VALID = [
    {"type": "gnss_fix", "t": 1.0, "x": 10.0, "y": -3.5},
    {"type": "gnss_fix", "t": 1.0, "x": 10.0, "y": -3.5, "std": 5.0},
    {"type": "odometer", "t": 1.0, "distance": 3.0},
    {"type": "odometer", "t": 1.0, "speed": 15.0},
    {"type": "v2v_range", "t": 1.0, "peer_vehicle_id": "car-2", "range": 120.0},
    {"type": "v2v_range", "t": 1.0, "peer_vehicle_id": "car-2", "toa": 4.0e-7},
    {"type": "rsu_range", "t": 1.0, "rsu_id": "RSU1", "range": 80.0},
]

INVALID: list[tuple[dict[str, Any], str, str]] = [
    ({"type": "odometer", "t": 1.0}, "measurements[0].speed", "neither"),
    ({"type": "odometer", "t": 1.0, "distance": 1.0, "speed": 2.0}, "measurements[0].speed", "both"),
    ({"type": "odometer", "t": 1.0, "speed": -1.0}, "measurements[0].speed", "greater than or equal"),
    ({"type": "v2v_range", "t": 1.0, "peer_vehicle_id": "b"}, "measurements[0].toa", "neither"),
    (
        {"type": "v2v_range", "t": 1.0, "peer_vehicle_id": "b", "range": 1.0, "toa": 1e-9},
        "measurements[0].toa",
        "both",
    ),
    ({"type": "v2v_range", "t": 1.0, "peer_vehicle_id": "b", "toa": 1.0}, "measurements[0].toa", "less than"),
    (
        {"type": "v2v_range", "t": 1.0, "peer_vehicle_id": "", "range": 1.0},
        "measurements[0].peer_vehicle_id",
        "match",
    ),
    ({"type": "gnss_fix", "t": 1.0, "x": 1.0}, "measurements[0].y", "required"),
    ({"type": "gnss_fix", "t": 1.0, "x": 1.0, "y": 2.0, "std": 0.0}, "measurements[0].std", "greater than"),
    ({"type": "gnss_fix", "t": 1.0, "x": 2e6, "y": 2.0}, "measurements[0].x", "less than"),
    (
        {"type": "rsu_range", "t": 1.0, "rsu_id": "RSU1", "range": -1.0},
        "measurements[0].range",
        "greater than",
    ),
    (
        {"type": "rsu_range", "t": 1.0, "rsu_id": "RSU1", "range": 1.0, "bearing": 0.0},
        "measurements[0].bearing",
        "Extra",
    ),
]


@pytest.mark.parametrize(("measurement", "field", "words"), INVALID)
def test_invalid_cooperative_measurements_name_the_field(client, measurement, field, words):
    session_id, auth = open_session(client)
    body = {"seq": 1, "measurements": [measurement]}
    response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=auth)
    problems = assert_error(response, 422, "invalid_request")["problems"]
    assert [p["field"] for p in problems] == [field], problems
    assert words in problems[0]["reason"]
    assert problems[0]["index"] == 0


def test_non_finite_toa_is_refused(client):
    session_id, auth = open_session(client)
    raw = '{"seq": 1, "measurements": [{"type": "v2v_range", "t": 1.0, "peer_vehicle_id": "b", "toa": NaN}]}'
    response = client.post(
        f"/v1/sessions/{session_id}/batches",
        content=raw,
        headers={**auth, "Content-Type": "application/json"},
    )
    assert_error(response, 422, "invalid_request")


@pytest.mark.parametrize("measurement", VALID)
def test_rsu_imu_refuses_cooperative_kinds_and_keeps_the_session(client, measurement):
    session_id, auth = open_session(client)
    body = batch_body(1, 0, 2)
    body["measurements"].append(measurement)
    index = len(body["measurements"]) - 1
    response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=auth)
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"] == [
        {
            "index": index,
            "field": f"measurements[{index}].type",
            "reason": f"the rsu_imu pipeline does not use {measurement['type']!r} measurements",
        }
    ]
    described = client.get(f"/v1/sessions/{session_id}", headers=auth).json()
    assert described["last_seq"] == 0 and described["epochs"] == 0
