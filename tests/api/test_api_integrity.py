"""Integrity on the wire: every rsu_imu fix carries protection_level_m and integrity; bad integrity
options are 422s naming the option."""

from __future__ import annotations

import pytest
from apihelp import ADMIN, assert_error, batch_observations, open_session, wire


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"integrity_risk": 0.5}, "options.integrity_risk"),
        ({"integrity_risk": 1e-12}, "options.integrity_risk"),
        ({"alert_limit_m": -1.0}, "options.alert_limit_m"),
        ({"fault_probability": 0.2}, "options.fault_probability"),
        ({"false_alarm_probability": 0.0}, "options.false_alarm_probability"),
        ({"fault_exclusion_s": -1.0}, "options.fault_exclusion_s"),
        ({"integrity_jerk_psd": 0.0}, "options.integrity_jerk_psd"),
    ],
)
def test_integrity_options_out_of_bounds_are_422_naming_the_option(client, options, field):
    response = client.post(
        "/v1/sessions", json={"vehicle_id": "car-9", "pipeline": "rsu_imu", "options": options}, headers=ADMIN
    )
    error = assert_error(response, 422, "invalid_request")
    assert field in {p["field"] for p in error["problems"]}, error


def test_fixes_carry_a_protection_level_within_the_alert_limit(client):
    session_id, token = open_session(client, pipeline="rsu_imu", options={"integrity": True})
    body = {"seq": 1, "measurements": [wire(o) for o in batch_observations(0, 60)]}
    response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token)
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert fixes[0]["integrity"] == "unavailable" and fixes[0]["protection_level_m"] is None
    settled = fixes[20:]
    assert all(f["integrity"] == "ok" for f in settled), [f["integrity"] for f in settled]
    assert all(0.0 < f["protection_level_m"] <= 1.5 for f in settled)


def test_without_the_monitor_fixes_say_unavailable_and_the_state_has_no_bank(client):
    """integrity off: no protection level and no sub-filters in the stored state; on (the default): both."""
    session_id, token = open_session(
        client, pipeline="rsu_imu", vehicle_id="car-off", options={"integrity": False}
    )
    body = {"seq": 1, "measurements": [wire(o) for o in batch_observations(0, 30)]}
    response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token)
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert {f["integrity"] for f in fixes} == {"unavailable"}
    assert {f["protection_level_m"] for f in fixes} == {None}
    on_id, on_token = open_session(client, pipeline="rsu_imu", vehicle_id="car-on")
    response = client.post(f"/v1/sessions/{on_id}/batches", json=body, headers=on_token)
    assert response.status_code == 200, response.text
    assert response.json()["fixes"][-1]["integrity"] == "ok"


@pytest.mark.parametrize("pipeline", ["v2v_coop", "v2x_federated"])
@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"integrity_risk": 0.5}, "options.integrity_risk"),
        ({"alert_limit_m": -1.0}, "options.alert_limit_m"),
        ({"fault_probability": 0.0}, "options.fault_probability"),
        ({"false_alarm_probability": 0.2}, "options.false_alarm_probability"),
    ],
)
def test_cooperative_integrity_options_out_of_bounds_are_422_naming_the_option(
    client, pipeline, options, field
):
    response = client.post(
        "/v1/sessions", json={"vehicle_id": "car-9", "pipeline": pipeline, "options": options}, headers=ADMIN
    )
    error = assert_error(response, 422, "invalid_request")
    assert field in {p["field"] for p in error["problems"]}, error


def test_cooperative_fixes_carry_a_protection_level(client):
    session_id, token = open_session(
        client, vehicle_id="car-a", pipeline="v2v_coop", options={"method": "gps_dr", "integrity": True}
    )
    batch = [{"type": "gnss_fix", "t": 0.2 * k, "x": 3.0 * k, "y": 0.0} for k in range(10)]
    response = client.post(
        f"/v1/sessions/{session_id}/batches", json={"seq": 1, "measurements": batch}, headers=token
    )
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert fixes[0]["integrity"] == "unavailable" and fixes[0]["protection_level_m"] is None
    # a fix checked against the prediction from the earlier ones: a bound, metres at a 3.5 m receiver
    assert all(f["integrity"] in ("ok", "alarm") and f["protection_level_m"] > 1.0 for f in fixes[1:])
