"""Late and out-of-order measurements over HTTP: revised fixes, too-late reports, the window's track."""

from __future__ import annotations

import math

from apihelp import ADMIN, assert_error, batch_observations, open_session, wire


def _post(client, session_id, seq, observations, headers, **extra):
    body = {"seq": seq, "measurements": [wire(o) for o in observations], **extra}
    return client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=headers)


def _split_late(first: int, count: int):
    """Epochs first..first+count-1 with the RSU measurements of the first two epochs held back."""
    observations = batch_observations(first, count)
    held_times = sorted({o.t for o in observations})[:2]
    held = [o for o in observations if o.t in held_times and o.kind == "rsu"]
    sent = [o for o in observations if o not in held]
    return sent, held


def test_late_measurements_give_revised_fixes_equal_to_time_order(client):
    in_order, in_order_token = open_session(client, vehicle_id="in-order")
    late, late_token = open_session(client, vehicle_id="late")
    assert _post(client, in_order, 1, batch_observations(0, 10), in_order_token).status_code == 200
    assert _post(client, late, 1, batch_observations(0, 10), late_token).status_code == 200
    expected = _post(client, in_order, 2, batch_observations(10, 6), in_order_token).json()["fixes"]

    sent, held = _split_late(10, 4)
    first = _post(client, late, 2, sent, late_token)
    assert first.status_code == 200, first.text
    assert not any(f["revised"] for f in first.json()["fixes"])
    # The held RSU measurements arrive with the next two epochs, in reverse order for good measure.
    second = _post(client, late, 3, [*batch_observations(14, 2), *reversed(held)], late_token)
    assert second.status_code == 200, second.text
    fixes = second.json()["fixes"]
    times = [f["t"] for f in fixes]
    assert times == sorted(times)
    revised = [f for f in fixes if f["revised"]]
    assert [f["t"] for f in revised] == sorted({o.t for o in batch_observations(10, 4)})
    assert [f["revised"] for f in fixes[-2:]] == [False, False]
    # the revised fixes report the late measurements by their index in this batch
    late_indices = {m["index"] for f in revised for m in f["measurements"]}
    assert late_indices == set(range(2 * 5 - 2, 2 * 5 - 2 + len(held))) or late_indices == set(
        range(len(batch_observations(14, 2)), len(batch_observations(14, 2)) + len(held))
    )
    last = {f["t"]: f for f in [*first.json()["fixes"], *fixes]}
    for fix in expected:
        got = last[fix["t"]]
        for name in ("x", "y", "vx", "vy"):
            assert math.isclose(got[name], fix[name], rel_tol=0, abs_tol=1e-9), (fix["t"], name)
    # counters count epochs once, revisions apart
    info = client.get(f"/v1/sessions/{late}", headers=late_token).json()
    assert info["epochs"] == 16
    assert info["last_fix"]["t"] == expected[-1]["t"]


def test_too_late_is_reported_unused_and_the_rest_applied(client):
    session_id, token = open_session(client)
    assert _post(client, session_id, 1, batch_observations(0, 40), token).status_code == 200
    stale = batch_observations(2, 1)[0]  # 37 epochs (1.85 s) older than the newest: beyond the 1 s window
    response = _post(client, session_id, 2, [*batch_observations(40, 1), stale], token)
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert len(fixes) == 1 and not fixes[0]["revised"]
    report = [m for m in fixes[0]["measurements"] if not m["used"]]
    assert len(report) == 1 and report[0]["index"] == len(batch_observations(40, 1))
    assert report[0]["reason"].startswith("too late") and "max_delay_s 1 s" in report[0]["reason"]
    # only too-late data: the newest fix again, unchanged, carrying the report
    again = _post(client, session_id, 3, [stale], token)
    assert again.status_code == 200, again.text
    only = again.json()["fixes"]
    assert len(only) == 1 and only[0]["revised"] and only[0]["t"] == fixes[0]["t"]
    assert only[0]["x"] == fixes[0]["x"] and only[0]["measurements"][0]["used"] is False


def test_malformed_late_measurement_refuses_the_batch(client):
    session_id, token = open_session(client)
    assert _post(client, session_id, 1, batch_observations(0, 40), token).status_code == 200
    before = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    stale = wire(batch_observations(2, 1)[0]) | {"rsu_id": "NOWHERE"}
    fresh = [wire(o) for o in batch_observations(40, 1)]
    body = {"seq": 2, "measurements": [*fresh, stale]}
    error = assert_error(
        client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token), 422, "invalid_request"
    )
    assert {(p["index"], p["field"]) for p in error["problems"]} == {
        (len(fresh), f"measurements[{len(fresh)}].rsu_id")
    }
    after = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    assert after == before


def test_lag_window_options_are_bounded(client):
    for options, field in (
        ({"max_delay_s": 11}, "options.max_delay_s"),
        ({"max_window_epochs": 0}, "options.max_window_epochs"),
        ({"max_lead_s": 0.5}, "options.max_lead_s"),
    ):
        response = client.post(
            "/v1/sessions",
            json={"vehicle_id": "car-9", "pipeline": "rsu_imu", "options": options},
            headers=ADMIN,
        )
        error = assert_error(response, 422, "invalid_request")
        assert field in {p["field"] for p in error["problems"]}, error


def test_a_measurement_far_ahead_of_its_batch_is_refused(client):
    session_id, token = open_session(client)
    observations = batch_observations(0, 3)
    ahead = wire(batch_observations(3, 1)[-1]) | {"t": observations[-1].t + 30.0}
    body = {"seq": 1, "measurements": [*(wire(o) for o in observations), ahead]}
    error = assert_error(
        client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token), 422, "invalid_request"
    )
    assert [(p["index"], p["field"]) for p in error["problems"]] == [
        (len(observations), f"measurements[{len(observations)}].t")
    ]
    assert "max_lead_s" in error["problems"][0]["reason"]


def test_track_filtered_equals_the_fixes_served_and_smoothed_differs(client):
    session_id, token = open_session(client)
    served = []
    for seq, first in enumerate(range(0, 40, 10), start=1):
        served += _post(client, session_id, seq, batch_observations(first, 10), token).json()["fixes"]
    response = client.get(f"/v1/sessions/{session_id}/track", headers=token)
    assert response.status_code == 200, response.text
    track = response.json()
    assert track["smoothed"] is False and track["max_delay_s"] == 1.0 and track["end_t"] == served[-1]["t"]
    by_t = {f["t"]: f for f in served}
    assert track["fixes"] and track["fixes"][0]["t"] == track["start_t"]
    assert track["end_t"] - track["start_t"] >= 1.0 - 1e-9
    for fix in track["fixes"]:
        assert fix["x"] == by_t[fix["t"]]["x"] and fix["measurements"] == []
        assert fix["state"] is not None
    smoothed = client.get(
        f"/v1/sessions/{session_id}/track", params={"smoothed": "true"}, headers=ADMIN
    ).json()
    assert smoothed["smoothed"] is True
    assert [f["t"] for f in smoothed["fixes"]] == [f["t"] for f in track["fixes"]]
    assert smoothed["fixes"][0]["x"] != track["fixes"][0]["x"]
    assert smoothed["fixes"][-1]["x"] == track["fixes"][-1]["x"] or math.isclose(
        smoothed["fixes"][-1]["x"], track["fixes"][-1]["x"], abs_tol=1e-9
    )


def test_track_needs_the_sessions_credential_and_known_parameters(client):
    session_id, token = open_session(client, vehicle_id="car-1")
    _, other = open_session(client, vehicle_id="car-2")
    assert client.get(f"/v1/sessions/{session_id}/track").status_code == 401
    assert client.get(f"/v1/sessions/{session_id}/track", headers=other).status_code in (401, 403)
    assert_error(
        client.get(f"/v1/sessions/{session_id}/track", params={"smooth": "true"}, headers=token),
        422,
        "invalid_request",
    )
    assert_error(
        client.get(f"/v1/sessions/{session_id}/track", params={"smoothed": "maybe"}, headers=token),
        422,
        "invalid_request",
    )
    empty = client.get(f"/v1/sessions/{session_id}/track", headers=token).json()
    assert empty["fixes"] == [] and empty["start_t"] is None and empty["end_t"] is None


def test_smoothing_a_pipeline_without_a_smoother_is_a_422(client):
    pipelines = {p["name"]: p for p in client.get("/v1/pipelines").json()["pipelines"]}
    assert pipelines["rsu_imu"]["smoother"] is True
    without = sorted(name for name, p in pipelines.items() if not p["smoother"])
    if not without:
        return
    session_id, token = open_session(client, vehicle_id="coop-1", pipeline=without[0])
    error = assert_error(
        client.get(f"/v1/sessions/{session_id}/track", params={"smoothed": "true"}, headers=token),
        422,
        "invalid_request",
    )
    assert error["problems"][0]["field"] == "smoothed"


def test_a_track_of_an_unreadable_state_is_a_409_like_a_batch(client):
    import dataclasses

    from edgepos.pipelines import lag

    session_id, token = open_session(client)
    assert _post(client, session_id, 1, batch_observations(0, 5), token).status_code == 200
    store = client.app.state.context.store
    record = client.portal.call(store.get, session_id)
    window = lag._unpack(record.state)
    for checkpoint in window.checkpoints:
        checkpoint.state = b"garbage"
    window.current = b"garbage"
    damaged = dataclasses.replace(record, state=lag._pack(window))
    assert client.portal.call(store.compare_and_set, damaged, record.version)
    for response in (
        client.get(f"/v1/sessions/{session_id}/track", headers=token),
        _post(client, session_id, 2, batch_observations(5, 1), token),
    ):
        error = assert_error(response, 409, "conflict")
        assert "cannot read the session's stored filter state" in error["message"]
