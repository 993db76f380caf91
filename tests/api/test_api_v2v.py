"""The v2v_coop pipeline through the API: ranges by TOA, bad input refused by field with the session
left as it was, and the pipeline listed with its methods."""

from __future__ import annotations

from apihelp import ADMIN, assert_error, open_session


def test_v2v_session_fixes_and_refusals(client):
    session_id, auth = open_session(
        client, vehicle_id="car-a", pipeline="v2v_coop", options={"method": "ukf"}
    )
    batch = [
        {"type": "gnss_fix", "t": 0.0, "x": 0.0, "y": 0.0},
        {"type": "gnss_fix", "t": 0.2, "x": 3.0, "y": 3.0},
        {"type": "v2v_range", "t": 0.2, "peer_vehicle_id": "car-b", "toa": 1e-7},
    ]
    response = client.post(
        f"/v1/sessions/{session_id}/batches", json={"seq": 1, "measurements": batch}, headers=auth
    )
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert [f["status"] for f in fixes] == ["initialised", "tracking"]
    assert "no live session" in fixes[1]["measurements"][1]["reason"]
    before = client.get(f"/v1/sessions/{session_id}", headers=auth).json()
    bad = [{"type": "v2v_range", "t": 0.4, "peer_vehicle_id": "car-b", "range": -1.0}]
    response = client.post(
        f"/v1/sessions/{session_id}/batches", json={"seq": 2, "measurements": bad}, headers=auth
    )
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"][0]["field"].startswith("measurements[0]")
    rsu = [{"type": "rsu", "t": 0.4, "rsu_id": "R", "range": 1.0, "bearing": 0.0}]
    response = client.post(
        f"/v1/sessions/{session_id}/batches", json={"seq": 2, "measurements": rsu}, headers=auth
    )
    assert 400 <= response.status_code < 500
    assert client.get(f"/v1/sessions/{session_id}", headers=auth).json() == before


def test_v2v_pipeline_is_listed_with_its_methods(client):
    pipelines = {p["name"]: p for p in client.get("/v1/pipelines").json()["pipelines"]}
    method = next(o for o in pipelines["v2v_coop"]["options"] if o["name"] == "method")
    assert method["default"] == "aug_ukf" and set(method["choices"]) == {"gps", "gps_dr", "ukf", "aug_ukf"}
    assert set(pipelines["v2v_coop"]["measurement_types"]) == {"gnss_fix", "gyro", "odometer", "v2v_range"}


def test_bad_v2v_option_names_the_option(client):
    response = client.post(
        "/v1/sessions",
        json={"vehicle_id": "car-1", "pipeline": "v2v_coop", "options": {"range_std": 0}},
        headers=ADMIN,
    )
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"][0]["field"] == "options.range_std"
