"""The v2x_federated pipeline through the API: fixes with per-measurement reasons, bad input as a
4xx that names the field and leaves the session as it was, late measurements filtered at their time."""

from __future__ import annotations

from apihelp import ADMIN, NO_DOPPLER, assert_error, open_session


def _post(client, session_id, auth, seq, measurements):
    return client.post(
        f"/v1/sessions/{session_id}/batches", json={"seq": seq, "measurements": measurements}, headers=auth
    )


def test_federated_session_tracks_and_explains(client):
    session_id, auth = open_session(client, pipeline="v2x_federated", options={"feedback": True})
    response = _post(
        client,
        session_id,
        auth,
        1,
        [
            {"type": "gnss_fix", "t": 0.0, "x": 0.0, "y": 0.0},
            {"type": "gnss_fix", "t": 0.2, "x": 2.0, "y": 0.1},
            {"type": "gyro", "t": 0.2, "yaw_rate": 0.0},
            {"type": "odometer", "t": 0.2, "speed": 10.0},
            {"type": "v2v_range", "t": 0.2, "peer_vehicle_id": "nobody", "range": 30.0},
        ],
    )
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert [f["status"] for f in fixes] == ["initialised", "tracking"]
    text = str(fixes[1])
    assert "no live session" in text


def test_federated_bad_input_is_4xx_and_keeps_the_session(client):
    session_id, auth = open_session(client, pipeline="v2x_federated")
    assert (
        _post(client, session_id, auth, 1, [{"type": "gnss_fix", "t": 1.0, "x": 0.0, "y": 0.0}]).status_code
        == 200
    )
    before = client.get(f"/v1/sessions/{session_id}", headers=auth).json()
    bad_batches = [
        # a measurement far ahead of the rest of its batch (a clock error; max_lead_s 10 s)
        (
            [
                {"type": "gnss_fix", "t": 1.5, "x": 0.0, "y": 0.0},
                {"type": "gnss_fix", "t": 30.0, "x": 0.0, "y": 0.0},
            ],
            "measurements[1].t",
        ),
        # a kind the pipeline does not take
        ([{"type": "rsu", "t": 2.0, "rsu_id": "R", "range": 1.0, "bearing": 0.0}], "measurements[0].type"),
        # the same, too late for the lag window: still refused, and the good rest is not applied
        (
            [
                {"type": "rsu", "t": -5.0, "rsu_id": "R", "range": 1.0, "bearing": 0.0},
                {"type": "gnss_fix", "t": 1.5, "x": 0.0, "y": 0.0},
            ],
            "measurements[0].type",
        ),
    ]
    for measurements, field in bad_batches:
        response = _post(client, session_id, auth, 2, measurements)
        assert 400 <= response.status_code < 500
        assert [p["field"] for p in response.json()["error"]["problems"]] == [field]
        assert client.get(f"/v1/sessions/{session_id}", headers=auth).json() == before


def test_federated_time_going_back_is_late_or_too_late_not_bad_input(client):
    """Before the lag window, t=0.5 after t=1.0 was refused: now, within max_delay_s (1 s) it is filtered at its
    own time (the fix at 1.0 comes back revised), and beyond it it is reported unused in the newest fix while
    the rest of the batch is applied."""
    session_id, auth = open_session(client, pipeline="v2x_federated")
    assert (
        _post(client, session_id, auth, 1, [{"type": "gnss_fix", "t": 1.0, "x": 0.0, "y": 0.0}]).status_code
        == 200
    )
    response = _post(client, session_id, auth, 2, [{"type": "gnss_fix", "t": 0.5, "x": 0.0, "y": 0.0}])
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert [(f["t"], f["revised"]) for f in fixes] == [(0.5, False), (1.0, True)]
    assert fixes[0]["measurements"] == [
        {"index": 0, "type": "gnss_fix", "used": True, "reason": None, **NO_DOPPLER}
    ]
    response = _post(
        client,
        session_id,
        auth,
        3,
        [
            {"type": "gnss_fix", "t": -1.0, "x": 0.0, "y": 0.0},
            {"type": "gnss_fix", "t": 1.2, "x": 0.1, "y": 0.0},
        ],
    )
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert [(f["t"], f["revised"]) for f in fixes] == [(1.2, False)]
    uses = fixes[0]["measurements"]
    assert [(u["index"], u["used"]) for u in uses] == [(0, False), (1, True)]
    assert uses[0]["reason"].startswith("too late: ")
    info = client.get(f"/v1/sessions/{session_id}", headers=auth).json()
    assert (info["last_seq"], info["epochs"], info["t"]) == (3, 3, 1.2)


def test_federated_bad_option_names_the_option(client):
    response = client.post(
        "/v1/sessions",
        json={"vehicle_id": "car-1", "pipeline": "v2x_federated", "options": {"dr_share": 2}},
        headers=ADMIN,
    )
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"][0]["field"] == "options.dr_share"
