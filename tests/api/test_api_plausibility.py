"""Physical plausibility on the wire: the options are listed for every pipeline, a far initial state is a
422 naming its fields, a run-off fix is served as "diverged" with the reason (and never published as the
vehicle's track), and a jump of the clock is refused with the session left as it was."""

from __future__ import annotations

import asyncio

from apihelp import ADMIN, assert_error, batch_body, open_session, scenario

NEW_OPTIONS = {"max_speed_mps", "max_acceleration_mps2", "site_radius_m", "max_time_jump_s", "on_divergence"}


def _post(client, session_id, body, headers):
    return client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=headers)


def test_every_pipeline_lists_the_plausibility_options(client):
    pipelines = client.get("/v1/pipelines").json()["pipelines"]
    assert {p["name"] for p in pipelines} == {"rsu_imu", "v2v_coop", "v2x_federated", "gnss_tight"}
    for pipeline in pipelines:
        options = {o["name"]: o for o in pipeline["options"]}
        assert NEW_OPTIONS <= set(options), pipeline["name"]
        assert options["max_speed_mps"]["default"] == 150.0
        assert options["site_radius_m"]["minimum"] == 10.0 and options["site_radius_m"]["maximum"] == 2.0e6
        assert options["on_divergence"]["choices"] == ["reset", "report"]


def test_an_initial_state_far_outside_the_site_is_a_422_naming_it(client):
    far = {"x": 1.0e6, "y": 1.0e6, "vx": 10.0, "vy": 0.0}
    response = client.post("/v1/sessions", json={"vehicle_id": "car-1", "initial_state": far}, headers=ADMIN)
    error = assert_error(response, 422, "invalid_request")
    assert [(p["index"], p["field"]) for p in error["problems"]] == [
        (None, "initial_state.x"),
        (None, "initial_state.y"),
    ]
    assert "site_radius_m" in error["problems"][0]["reason"]
    assert client.get("/v1/sessions", headers=ADMIN).json()["sessions"] == []
    # with a site radius that covers it, the session opens and the options say so
    body = {"vehicle_id": "car-1", "initial_state": far, "options": {"site_radius_m": 2.0e6}}
    response = client.post("/v1/sessions", json=body, headers=ADMIN)
    assert response.status_code == 201, response.text
    assert response.json()["options"]["site_radius_m"] == 2.0e6


def test_a_run_off_fix_is_served_diverged_and_the_session_starts_again(client):
    far = {"x": 1.0e6, "y": 1.0e6, "vx": 10.0, "vy": 0.0}
    session_id, token = open_session(client, initial_state=far, options={"site_radius_m": 2.0e6})
    response = _post(client, session_id, batch_body(1, 0, 8), token)
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert [f["status"] for f in fixes] == ["tracking", "diverged", "initialised"] + ["tracking"] * 5
    diverged = fixes[1]
    assert diverged["speed"] > 1e4
    assert "max_speed_mps" in diverged["divergence"] and "session was reset" in diverged["divergence"]
    assert all(f["divergence"] is None for f in fixes if f is not diverged)
    more = _post(client, session_id, batch_body(2, 8, 5), token).json()["fixes"]
    assert {f["status"] for f in more} == {"tracking"}
    truth = scenario().truth  # epoch k of the batches is the truth's point k + 1
    assert abs(more[-1]["x"] - truth.x[13]) < 1.0 and abs(more[-1]["y"] - truth.y[13]) < 1.0
    # a session whose latest fix diverged is listed and described as such
    session_id, token = open_session(
        client, vehicle_id="car-2", initial_state=far, options={"site_radius_m": 2.0e6}
    )
    assert _post(client, session_id, batch_body(1, 0, 2), token).status_code == 200
    described = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    assert described["last_fix"]["status"] == "diverged" and described["initialised"] is False
    assert described["last_fix"]["divergence"].startswith("speed ")
    listed = {s["session_id"]: s for s in client.get("/v1/sessions", headers=ADMIN).json()["sessions"]}
    assert listed[session_id]["status"] == "diverged"


def test_report_only_marks_the_fixes(client):
    far = {"x": 1.0e6, "y": 1.0e6, "vx": 10.0, "vy": 0.0}
    options = {"site_radius_m": 2.0e6, "on_divergence": "report"}
    session_id, token = open_session(client, initial_state=far, options=options)
    fixes = _post(client, session_id, batch_body(1, 0, 4), token).json()["fixes"]
    assert [f["status"] for f in fixes] == ["tracking"] + ["diverged"] * 3
    assert all("reported only" in f["divergence"] for f in fixes[1:])


def test_a_diverged_fix_is_not_published_to_neighbours(client):
    session_id, token = open_session(
        client, vehicle_id="car-a", pipeline="v2v_coop", options={"method": "ukf"}
    )
    fixes = [(0.0, 0.0, 0.0), (0.2, 3.0, 3.0), (0.4, 6.0, 6.0), (0.6, 3000.0, 6.0), (0.8, 3003.0, 6.0)]
    batch = [{"type": "gnss_fix", "t": t, "x": x, "y": y} for t, x, y in fixes]
    response = _post(client, session_id, {"seq": 1, "measurements": batch}, token)
    assert response.status_code == 200, response.text
    statuses = [f["status"] for f in response.json()["fixes"]]
    assert statuses == ["initialised", "tracking", "tracking", "diverged", "initialised"]
    published = asyncio.run(client.app.state.context.store.get_tracks(["car-a"]))["car-a"]
    assert [p.t for p in published.points] == [0.0, 0.2, 0.4, 0.8]


def test_a_jump_of_the_clock_is_refused_and_the_session_goes_on(client):
    session_id, token = open_session(client)
    assert _post(client, session_id, batch_body(1, 0, 3), token).status_code == 200
    before = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    jump = batch_body(2, 3, 1)
    for measurement in jump["measurements"]:
        measurement["t"] = 1.0e10
    error = assert_error(_post(client, session_id, jump, token), 422, "invalid_request")
    assert [p["field"] for p in error["problems"]] == [
        f"measurements[{i}].t" for i in range(len(jump["measurements"]))
    ]
    assert "max_time_jump_s" in error["problems"][0]["reason"]
    assert client.get(f"/v1/sessions/{session_id}", headers=token).json() == before
    response = _post(client, session_id, batch_body(2, 3, 3), token)
    assert response.status_code == 200 and {f["status"] for f in response.json()["fixes"]} == {"tracking"}
