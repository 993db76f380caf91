"""Sessions: creation with options and initial state, reading, deleting, limits, expiry, access."""

from __future__ import annotations

import pytest
from apifakes import CreateFailingPipeline, ResolveFailingPipeline
from apihelp import ADMIN, assert_error, batch_body, bearer, make_settings, open_session, rsu_payload
from edgepos.api.app import create_app
from edgepos.pipelines.registry import get_pipeline
from edgepos.store import MemoryStore
from fastapi.testclient import TestClient


def test_create_returns_token_and_effective_options(client):
    response = client.post(
        "/v1/sessions", json={"vehicle_id": "car-7", "options": {"filter": "ukf"}}, headers=ADMIN
    )
    assert response.status_code == 201
    body = response.json()
    assert set(body) == {
        "session_id",
        "token",
        "vehicle_id",
        "pipeline",
        "options",
        "created_at",
        "superseded",
    }
    assert body["superseded"] is None
    assert body["vehicle_id"] == "car-7" and body["pipeline"] == "rsu_imu"
    assert body["options"] == get_pipeline("rsu_imu").resolve_options({"filter": "ukf"})
    assert body["token"].startswith(body["session_id"] + ".")


def test_new_session_reads_back_empty(client):
    session_id, token = open_session(client, initial_state={"x": 1.0, "y": 2.0, "vx": 10.0, "vy": 0.0})
    body = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    assert body["last_seq"] == 0 and body["batches"] == 0 and body["epochs"] == 0
    assert body["initialised"] is True and body["t"] is None and body["last_fix"] is None
    assert body["model_probabilities"] == pytest.approx({"ca": 1 / 3, "at": 1 / 3, "singer": 1 / 3})
    assert body["created_at"] == body["updated_at"]


def test_session_without_initial_state_starts_uninitialised(client):
    session_id, token = open_session(client)
    assert client.get(f"/v1/sessions/{session_id}", headers=token).json()["initialised"] is False


def test_session_counts_batches_and_keeps_the_last_fix(client):
    session_id, token = open_session(client)
    fixes = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 5), headers=token).json()[
        "fixes"
    ]
    body = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    assert body["last_seq"] == 1 and body["batches"] == 1 and body["epochs"] == 5
    assert body["last_fix"] == fixes[-1]
    assert body["t"] == fixes[-1]["t"] and body["initialised"] is True
    assert body["model_probabilities"] == fixes[-1]["model_probabilities"]
    assert body["updated_at"] >= body["created_at"]


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"filter": "kalman"}, "options.filter"),
        ({"max_rsus": 0}, "options.max_rsus"),
        ({"no_such_option": 1}, "options.no_such_option"),
        ({"gate_probability": "high"}, "options.gate_probability"),
        ({"filter_params": {"nonsense": 1}}, "options.filter_params.nonsense"),
        ({"model_params": {"singer": {"sigma": 1e200}}}, "options.model_params.singer.sigma"),
    ],
)
def test_bad_option_is_refused(client, options, field):
    response = client.post("/v1/sessions", json={"vehicle_id": "car", "options": options}, headers=ADMIN)
    error = assert_error(response, 422, "invalid_request")
    assert field in {p["field"] for p in error["problems"]}
    assert all(p["index"] is None for p in error["problems"])


def test_non_finite_option_is_refused(client):
    content = '{"vehicle_id": "car", "options": {"transition_diagonal": NaN}}'
    response = client.post(
        "/v1/sessions", content=content, headers={**ADMIN, "content-type": "application/json"}
    )
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"][0]["field"] == "options"


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"vehicle_id": "car", "pipeline": "nope"}, "pipeline"),
        ({"vehicle_id": ""}, "vehicle_id"),
        ({}, "vehicle_id"),
        ({"vehicle_id": "car", "initial_state": {"x": 0, "y": 0, "vx": 0}}, "initial_state.vy"),
        (
            {"vehicle_id": "car", "initial_state": {"x": 0, "y": 0, "vx": 0, "vy": 0, "position_std": 0}},
            "initial_state.position_std",
        ),
        ({"vehicle_id": "car", "extra": True}, "extra"),
        ({"vehicle_id": 5}, "vehicle_id"),
    ],
)
def test_bad_session_body_is_refused(client, body, field):
    error = assert_error(client.post("/v1/sessions", json=body, headers=ADMIN), 422, "invalid_request")
    assert field in {p["field"] for p in error["problems"]}


def test_delete_with_own_token_then_gone(client):
    session_id, token = open_session(client)
    assert client.delete(f"/v1/sessions/{session_id}", headers=token).status_code == 204
    assert_error(client.get(f"/v1/sessions/{session_id}", headers=ADMIN), 404, "not_found")
    assert_error(client.delete(f"/v1/sessions/{session_id}", headers=ADMIN), 404, "not_found")
    # the token of a session that is gone is answered like any wrong token: nobody learns which ids exist
    assert_error(client.get(f"/v1/sessions/{session_id}", headers=token), 401, "unauthorized")


def test_admin_key_opens_any_session(client):
    session_id, _ = open_session(client)
    assert client.get(f"/v1/sessions/{session_id}", headers=ADMIN).status_code == 200
    response = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 2), headers=ADMIN)
    assert response.status_code == 200
    assert client.delete(f"/v1/sessions/{session_id}", headers=ADMIN).status_code == 204


def test_a_session_token_opens_only_its_session(client):
    first, first_token = open_session(client)
    second, second_token = open_session(client, vehicle_id="car-2")
    for method, path, body in (
        ("GET", f"/v1/sessions/{second}", None),
        ("DELETE", f"/v1/sessions/{second}", None),
        ("POST", f"/v1/sessions/{second}/batches", batch_body(1, 0, 1)),
    ):
        response = client.request(method, path, json=body, headers=first_token)
        assert_error(response, 403, "forbidden")
    assert client.get(f"/v1/sessions/{second}", headers=ADMIN).json()["last_seq"] == 0
    assert client.get(f"/v1/sessions/{first}", headers=first_token).status_code == 200
    assert client.get(f"/v1/sessions/{second}", headers=second_token).status_code == 200


def test_missing_or_wrong_credentials_are_401(client):
    session_id, _token = open_session(client)
    wrong_secret = bearer(f"{session_id}.not-the-secret")
    forged_other = bearer("f" * 32 + ".not-a-session")
    for headers in ({}, wrong_secret, forged_other, bearer("garbage"), {"Authorization": "Token abc"}):
        response = client.get(f"/v1/sessions/{session_id}", headers=headers)
        error = assert_error(response, 401, "unauthorized")
        assert response.headers["www-authenticate"] == "Bearer"
        assert "not-the-secret" not in error["message"]


def test_unknown_session_is_404_for_admin(client):
    assert_error(client.get("/v1/sessions/0123456789abcdef0123456789abcdef", headers=ADMIN), 404, "not_found")
    response = client.post("/v1/sessions/nope/batches", json=batch_body(1, 0, 1), headers=ADMIN)
    assert_error(response, 404, "not_found")


def test_max_sessions_gives_429(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, max_sessions=2))) as client:
        first, token = open_session(client)
        open_session(client, vehicle_id="car-2")
        refused = client.post("/v1/sessions", json={"vehicle_id": "car"}, headers=ADMIN)
        assert_error(refused, 429, "too_many_sessions")
        assert int(refused.headers["Retry-After"]) > 0
        assert client.delete(f"/v1/sessions/{first}", headers=token).status_code == 204
        open_session(client)


class FakeClock:
    def __init__(self) -> None:
        self.now = 1_000_000.0

    def __call__(self) -> float:
        return self.now


def test_idle_sessions_expire_after_the_ttl(tmp_path):
    clock = FakeClock()
    settings = make_settings(tmp_path, session_ttl_s=60.0, max_sessions=1)
    store = MemoryStore(settings.session_ttl_s, clock)
    with TestClient(create_app(settings, store=store)) as client:
        client.put("/v1/rsus", json={"rsus": []}, headers=ADMIN)
        session_id, token = open_session(client)
        clock.now += 50.0
        assert client.get(f"/v1/sessions/{session_id}", headers=token).status_code == 200
        assert_error(
            client.post("/v1/sessions", json={"vehicle_id": "car"}, headers=ADMIN), 429, "too_many_sessions"
        )
        clock.now += 11.0
        assert_error(client.get(f"/v1/sessions/{session_id}", headers=ADMIN), 404, "not_found")
        open_session(client)  # the expired one no longer counts


def test_a_batch_keeps_a_session_alive(tmp_path):
    clock = FakeClock()
    settings = make_settings(tmp_path, session_ttl_s=60.0)
    store = MemoryStore(settings.session_ttl_s, clock)
    with TestClient(create_app(settings, store=store)) as test_client:
        test_client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(test_client)
        clock.now += 50.0
        response = test_client.post(
            f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 1), headers=token
        )
        assert response.status_code == 200
        clock.now += 50.0
        assert (
            test_client.get(f"/v1/sessions/{session_id}", headers=token).json()["updated_at"] == 1_000_050.0
        )


@pytest.mark.parametrize(
    ("pipeline", "field"), [(ResolveFailingPipeline(), "options"), (CreateFailingPipeline(), "initial_state")]
)
def test_estimation_core_refusals_at_creation_are_422(tmp_path, pipeline, field):
    with TestClient(create_app(make_settings(tmp_path), pipelines={"rsu_imu": pipeline})) as client:
        body = {"vehicle_id": "car", "initial_state": {"x": 0.0, "y": 0.0, "vx": 1.0, "vy": 0.0}}
        error = assert_error(client.post("/v1/sessions", json=body, headers=ADMIN), 422, "invalid_request")
        assert [p["field"] for p in error["problems"]] == [field]
        assert "edgepos_active_sessions 0.0" in client.get("/metrics").text  # nothing was created


@pytest.mark.parametrize("name", ["rsu_imu", "gnss_tight", "v2v_coop", "v2x_federated"])
def test_a_session_can_be_opened_with_every_option_it_reports(client, name):
    """A client may send back all of a pipeline's effective options (gnss_tight has 69, more than the old
    limit of 64 keys, which refused such a body: the option fuzz test found it)."""
    from edgepos.api.schemas import MAX_OPTIONS

    options = get_pipeline(name).resolve_options({})
    assert len(options) < MAX_OPTIONS
    response = client.post(
        "/v1/sessions",
        json={"vehicle_id": f"all-{name}", "pipeline": name, "options": options},
        headers=ADMIN,
    )
    assert response.status_code == 201, response.text
    assert response.json()["options"] == options
