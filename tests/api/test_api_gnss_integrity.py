"""gnss_tight integrity on the wire (issue 21): bad monitor options are 422s naming the option, and tracked
fixes of the real recording carry protection_level_m and integrity."""

from __future__ import annotations

import pytest
from apihelp import open_session
from gnsswire import QUICK, assert_option_refused, measurements, quick_fixes, upload_ephemerides


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"integrity_risk": 0.5}, "options.integrity_risk"),
        ({"integrity_risk": 1e-12}, "options.integrity_risk"),
        ({"alert_limit_m": -1.0}, "options.alert_limit_m"),
        ({"satellite_fault_probability": 0.2}, "options.satellite_fault_probability"),
        ({"constellation_fault_probability": 0.0}, "options.constellation_fault_probability"),
        ({"false_alarm_probability": 0.0}, "options.false_alarm_probability"),
        ({"integrity_inflation": 0.5}, "options.integrity_inflation"),
        ({"fault_exclusion": "yes"}, "options.fault_exclusion"),
    ],
)
def test_gnss_integrity_options_out_of_bounds_are_422_naming_the_option(client, options, field):
    assert_option_refused(client, options, field)


def test_tracked_gnss_fixes_carry_a_protection_level(client):
    upload_ephemerides(client)
    fixes = quick_fixes(client, "car-1", {**QUICK, "alert_limit_m": 1000.0})
    assert fixes[0]["integrity"] == "unavailable" and fixes[0]["protection_level_m"] is None
    assert all(f["integrity"] == "ok" for f in fixes[2:]), [f["integrity"] for f in fixes]
    assert all(f["protection_level_m"] > 0.0 for f in fixes[2:])
    # at the default alert limit (5 m) the same fixes are in alarm: their protection level exceeds it
    other_id, other_token = open_session(client, pipeline="gnss_tight", vehicle_id="car-2", options=QUICK)
    body = {"seq": 1, "measurements": measurements(0, 4)}
    response = client.post(f"/v1/sessions/{other_id}/batches", json=body, headers=other_token)
    assert response.status_code == 200, response.text
    assert {f["integrity"] for f in response.json()["fixes"][2:]} == {"alarm"}
