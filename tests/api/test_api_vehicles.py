"""Who may speak for a vehicle: the registry, vehicle keys, one live session per vehicle, the
operator's session listing, and the abuse limits on failed authentications and session creations."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import jwt
import pytest
from apihelp import ADMIN, assert_error, batch_body, bearer, make_settings, open_session, rsu_payload
from cryptography.hazmat.primitives.asymmetric import ec
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from edgepos.api.vehicle_jwt import JwksError
from edgepos.loadgen.localredis import RedisServer, redis_binary
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st
from jwt.algorithms import ECAlgorithm
from pydantic import ValidationError

INVALID = "the bearer credential is not valid (unknown, revoked or expired key or token)"


def register(client: TestClient, vehicle_id: str) -> dict[str, str]:
    """Register a vehicle; returns the Authorization header of its key."""
    response = client.post("/v1/vehicles", json={"vehicle_id": vehicle_id}, headers=ADMIN)
    assert response.status_code == 201, response.text
    body = response.json()
    assert set(body) == {"vehicle_id", "key", "created_at", "key_issued_at"}
    assert body["vehicle_id"] == vehicle_id and body["key"].startswith("evk_") and len(body["key"]) > 40
    return bearer(body["key"])


def create(client: TestClient, vehicle_id: str, credential: dict[str, str] | None) -> object:
    return client.post("/v1/sessions", json={"vehicle_id": vehicle_id}, headers=credential or {})


def live_sessions(client: TestClient, **filters: str) -> list[dict[str, object]]:
    response = client.get("/v1/sessions", params=filters, headers=ADMIN)
    assert response.status_code == 200, response.text
    return response.json()["sessions"]


def test_a_registered_vehicle_opens_sessions_for_itself_only(client):
    key = register(client, "bus-42")
    created = create(client, "bus-42", key)
    assert created.status_code == 201, created.text
    refused = create(client, "bus-43", key)
    error = assert_error(refused, 403, "forbidden")
    assert "'bus-43'" in error["message"]
    assert [s["vehicle_id"] for s in live_sessions(client)] == ["bus-42"]


@pytest.mark.parametrize(
    "credential",
    [
        None,
        bearer("evk_not-a-registered-key"),
        bearer("no-prefix"),
        bearer("a.b.c"),
        {"Authorization": "Basic x"},
    ],
)
def test_opening_a_session_needs_a_valid_credential(client, credential):
    response = create(client, "car-1", credential)
    error = assert_error(response, 401, "unauthorized")
    assert response.headers["www-authenticate"] == "Bearer"
    if credential is not None and credential["Authorization"].startswith("Bearer"):
        assert error["message"] == INVALID
    assert live_sessions(client) == []


def test_the_registry_never_shows_a_key_and_refuses_duplicates(client):
    keys = [register(client, vehicle) for vehicle in ("v/3", "v 1", "v2")]
    listed = client.get("/v1/vehicles", headers=ADMIN).json()
    assert [v["vehicle_id"] for v in listed["vehicles"]] == ["v 1", "v/3", "v2"]
    assert listed["total"] == 3 and listed["next_after"] is None
    text = client.get("/v1/vehicles", headers=ADMIN).text
    assert all(key["Authorization"].split()[1] not in text for key in keys)
    one = client.get("/v1/vehicles/v%2F3", headers=ADMIN)
    assert one.status_code == 200 and set(one.json()) == {"vehicle_id", "created_at", "key_issued_at"}
    again = client.post("/v1/vehicles", json={"vehicle_id": "v2"}, headers=ADMIN)
    assert "/key" in assert_error(again, 409, "conflict")["message"]
    assert_error(client.get("/v1/vehicles/nobody", headers=ADMIN), 404, "not_found")


def test_vehicle_listing_pages(client):
    client.post(
        "/v1/vehicles/bulk",
        json={"vehicles": [{"vehicle_id": f"car-{n:03d}"} for n in range(25)]},
        headers=ADMIN,
    )
    seen, after = [], None
    while True:
        params = {"limit": 10, **({"after": after} if after else {})}
        page = client.get("/v1/vehicles", params=params, headers=ADMIN).json()
        seen += [v["vehicle_id"] for v in page["vehicles"]]
        assert page["total"] == 25
        after = page["next_after"]
        if after is None:
            break
    assert seen == [f"car-{n:03d}" for n in range(25)]


def test_bulk_import_registers_the_new_and_leaves_the_known(client):
    first = register(client, "known")
    response = client.post(
        "/v1/vehicles/bulk",
        json={"vehicles": [{"vehicle_id": "known"}, {"vehicle_id": "new-1"}]},
        headers=ADMIN,
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["already_registered"] == ["known"]
    assert [v["vehicle_id"] for v in body["registered"]] == ["new-1"]
    assert create(client, "known", first).status_code == 201  # the known vehicle's key is unchanged
    assert create(client, "new-1", bearer(body["registered"][0]["key"])).status_code == 201
    twice = {"vehicles": [{"vehicle_id": "a"}, {"vehicle_id": "a"}]}
    assert_error(client.post("/v1/vehicles/bulk", json=twice, headers=ADMIN), 422, "invalid_request")
    too_many = {"vehicles": [{"vehicle_id": f"x{n}"} for n in range(5001)]}
    assert_error(client.post("/v1/vehicles/bulk", json=too_many, headers=ADMIN), 422, "invalid_request")
    assert client.get("/v1/vehicles", headers=ADMIN).json()["total"] == 2


def test_rotating_a_key_retires_the_old_one_and_keeps_the_session(client):
    old_key = register(client, "taxi-7")
    session_id = create(client, "taxi-7", old_key).json()["session_id"]
    rotated = client.post("/v1/vehicles/taxi-7/key", headers=ADMIN)
    assert rotated.status_code == 200, rotated.text
    new_key = bearer(rotated.json()["key"])
    assert_error(create(client, "taxi-7", old_key), 401, "unauthorized")
    assert client.get(f"/v1/sessions/{session_id}", headers=ADMIN).status_code == 200
    assert create(client, "taxi-7", new_key).status_code == 201
    assert_error(client.post("/v1/vehicles/nobody/key", headers=ADMIN), 404, "not_found")


def test_revoking_a_vehicle_ends_its_session_and_key(client):
    key = register(client, "lost-1")
    created = create(client, "lost-1", key).json()
    token = bearer(created["token"])
    applied = client.post(
        f"/v1/sessions/{created['session_id']}/batches", json=batch_body(1, 0, 2), headers=token
    )
    assert applied.status_code == 200
    revoked = client.delete("/v1/vehicles/lost-1", headers=ADMIN)
    assert revoked.json() == {"vehicle_id": "lost-1", "ended_session": created["session_id"]}
    assert_error(
        client.post(f"/v1/sessions/{created['session_id']}/batches", json=batch_body(2, 2, 1), headers=token),
        401,
        "unauthorized",
    )
    assert_error(create(client, "lost-1", key), 401, "unauthorized")
    assert_error(client.delete("/v1/vehicles/lost-1", headers=ADMIN), 404, "not_found")
    assert live_sessions(client) == []


def test_a_newer_session_supersedes_the_older_one(client):
    key = register(client, "van-5")
    first = create(client, "van-5", key).json()
    second = create(client, "van-5", key).json()
    assert first["superseded"] is None and second["superseded"] == first["session_id"]
    old_token = bearer(first["token"])
    for method, path, body in (
        ("GET", f"/v1/sessions/{first['session_id']}", None),
        ("POST", f"/v1/sessions/{first['session_id']}/batches", batch_body(1, 0, 1)),
        ("DELETE", f"/v1/sessions/{first['session_id']}", None),
    ):
        error = assert_error(client.request(method, path, json=body, headers=old_token), 409, "superseded")
        assert second["session_id"] in error["message"]
    # a wrong secret for the superseded session learns nothing about its successor: it is answered
    # as any wrong token
    wrong = client.get(f"/v1/sessions/{first['session_id']}", headers=bearer(f"{first['session_id']}.wrong"))
    assert assert_error(wrong, 401, "unauthorized")["message"] == INVALID
    assert [s["session_id"] for s in live_sessions(client)] == [second["session_id"]]
    assert (
        client.get(f"/v1/sessions/{second['session_id']}", headers=bearer(second["token"])).status_code == 200
    )


def test_the_operator_lists_live_sessions_with_filters_and_pages(client):
    ids = {}
    for n in range(5):
        ids[f"car-{n}"], token = open_session(client, vehicle_id=f"car-{n}")
        if n == 0:
            client.post(f"/v1/sessions/{ids['car-0']}/batches", json=batch_body(1, 0, 3), headers=token)
    open_session(client, vehicle_id="gnss-1", pipeline="gnss_tight")
    everything = live_sessions(client)
    assert [s["session_id"] for s in everything] == sorted(s["session_id"] for s in everything)
    assert len(everything) == 6
    busy = live_sessions(client, vehicle_id="car-0")
    assert len(busy) == 1 and busy[0]["last_seq"] == 1 and busy[0]["epochs"] == 3
    assert busy[0]["status"] in {"initialised", "tracking"} and busy[0]["last_fix_t"] is not None
    assert {s["status"] for s in live_sessions(client, vehicle_id="car-1")} == {"new"}
    assert [s["vehicle_id"] for s in live_sessions(client, pipeline="gnss_tight")] == ["gnss-1"]
    pages, after = [], None
    while True:
        page = client.get(
            "/v1/sessions", params={"limit": 4, **({"after": after} if after else {})}, headers=ADMIN
        )
        pages.append(page.json()["sessions"])
        after = page.json()["next_after"]
        if after is None:
            break
    assert [len(p) for p in pages] == [4, 2]
    assert [s["session_id"] for p in pages for s in p] == [s["session_id"] for s in everything]
    assert_error(client.get("/v1/sessions", params={"limit": 0}, headers=ADMIN), 422, "invalid_request")
    misspelt = assert_error(
        client.get("/v1/sessions", params={"pipline": "gnss_tight"}, headers=ADMIN), 422, "invalid_request"
    )
    assert [p["field"] for p in misspelt["problems"]] == ["pipline"]


def test_only_the_admin_key_lists_sessions(client):
    key = register(client, "car-9")
    token = bearer(create(client, "car-9", key).json()["token"])
    assert (
        client.get("/v1/rsus", headers=key).status_code == 200
    )  # the site's map is readable by its vehicles
    for credential in (key, token):
        assert_error(client.get("/v1/sessions", headers=credential), 403, "forbidden")
        assert_error(client.get("/v1/vehicles", headers=credential), 403, "forbidden")
        assert_error(
            client.post("/v1/vehicles", json={"vehicle_id": "x"}, headers=credential), 403, "forbidden"
        )
    assert_error(client.get("/v1/sessions"), 401, "unauthorized")


def test_failed_authentications_are_limited_per_address(tmp_path, caplog):
    settings = make_settings(tmp_path, auth_failure_rate_per_s=0.01, auth_failure_burst=3)
    with TestClient(create_app(settings)) as client:
        key = register(client, "car-1")
        caplog.set_level(logging.WARNING, logger="edgepos.api")
        for attempt in range(3):
            assert_error(create(client, "car-1", bearer(f"evk_guess-{attempt}")), 401, "unauthorized")
        refused = create(client, "car-1", bearer("evk_guess-4"))
        assert_error(refused, 429, "rate_limited")  # the address is past its budget: back off
        assert int(refused.headers["Retry-After"]) >= 1
        # a valid key from that address still works: a fleet behind one NAT address is not locked
        # out by a stranger's failures (no rate of guessing finds a 256-bit key)
        assert create(client, "car-1", key).status_code == 201
        # a credential past its own budget is refused before it is even looked up
        for _ in range(3):
            create(client, "car-1", bearer("evk_revoked-in-a-loop"))
        again = create(client, "car-1", bearer("evk_revoked-in-a-loop"))
        assert "this credential failed too often" in assert_error(again, 429, "rate_limited")["message"]
        metrics = client.get("/metrics").text
        assert 'edgepos_auth_failures_total{reason="invalid"} 7.0' in metrics  # 3 + 1 + 3, not the last one
        assert 'edgepos_rate_limited_total{limit="auth_failures"}' in metrics
        logged = "\n".join(record.getMessage() + str(record.__dict__) for record in caplog.records)
        assert (
            "auth_failed" in logged and "evk_guess" not in logged and key["Authorization"][7:] not in logged
        )
        # the admin key is never locked out: an operator can always act
        assert client.get("/v1/vehicles", headers=ADMIN).status_code == 200


def test_session_creations_are_limited_per_vehicle_credential(tmp_path):
    settings = make_settings(tmp_path, session_create_rate_per_s=0.01, session_create_burst=2)
    with TestClient(create_app(settings)) as client:
        key = register(client, "car-1")
        assert create(client, "car-1", key).status_code == 201
        assert create(client, "car-1", key).status_code == 201
        refused = create(client, "car-1", key)
        assert "EDGEPOS_SESSION_CREATE_RATE_PER_S" in assert_error(refused, 429, "rate_limited")["message"]
        other = register(client, "car-2")
        assert create(client, "car-2", other).status_code == 201  # another vehicle has its own budget
        for _ in range(5):  # the admin key is not limited (operators, load tests)
            assert create(client, "car-1", ADMIN).status_code == 201


def test_open_mode_lets_anyone_open_a_session_on_loopback(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, vehicle_auth="open"))) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        created = create(client, "anyone", None)
        assert created.status_code == 201, created.text


@pytest.mark.parametrize("host", ["0.0.0.0", "192.0.2.10", "::", "edge.example"])
def test_open_mode_is_refused_off_loopback_unless_lab(tmp_path, host):
    with pytest.raises(ValidationError, match="non-loopback"):
        Settings(admin_key="k" * 20, host=host, vehicle_auth="open")
    assert Settings(admin_key="k" * 20, host=host, vehicle_auth="open", lab=True).vehicle_auth == "open"
    for loopback in ("127.0.0.1", "127.8.0.1", "::1", "localhost"):
        assert Settings(admin_key="k" * 20, host=loopback, vehicle_auth="open").vehicle_auth == "open"


def test_jwt_mode_needs_a_key_set(tmp_path: Path):
    with pytest.raises(ValidationError, match="EDGEPOS_VEHICLE_JWKS"):
        Settings(admin_key="k" * 20, vehicle_auth="jwt")


# -- every store ------------------------------------------------------------------------------------
@pytest.fixture(params=["memory", "sqlite", "redis"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    if request.param == "memory":
        yield "memory"
    elif request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'edgepos.db'}"
    else:
        binary = redis_binary()
        if binary is None:
            pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
        with RedisServer(binary, tmp_path / "redis", "--save", "", "--appendonly", "no") as server:
            yield server.url("vehicles:")


def test_a_revoked_vehicles_session_and_track_are_gone_in_every_store(tmp_path, store_url):
    """Revocation ends the live session and withdraws the published track, whatever the store: a
    neighbour ranging to the revoked vehicle no longer finds it."""
    with TestClient(create_app(make_settings(tmp_path, store=store_url))) as client:
        key = register(client, "bus-42")
        body = {"vehicle_id": "bus-42", "pipeline": "v2v_coop", "options": {"method": "gps"}}
        created = client.post("/v1/sessions", json=body, headers=key).json()
        token = bearer(created["token"])
        fix = {"seq": 1, "measurements": [{"type": "gnss_fix", "t": 0.0, "x": 10.0, "y": 5.0}]}
        assert (
            client.post(f"/v1/sessions/{created['session_id']}/batches", json=fix, headers=token).status_code
            == 200
        )
        store = client.app.state.context.store
        assert "bus-42" in client.portal.call(store.get_tracks, ["bus-42"])
        assert (
            client.delete("/v1/vehicles/bus-42", headers=ADMIN).json()["ended_session"]
            == created["session_id"]
        )
        assert_error(client.get(f"/v1/sessions/{created['session_id']}", headers=token), 401, "unauthorized")
        assert_error(client.get(f"/v1/sessions/{created['session_id']}", headers=ADMIN), 404, "not_found")
        assert client.portal.call(store.get_tracks, ["bus-42"]) == {}
        assert live_sessions(client) == []
        assert_error(client.post("/v1/sessions", json=body, headers=key), 401, "unauthorized")


# -- fleet-signed tokens (EDGEPOS_VEHICLE_AUTH=jwt) -------------------------------------------------------
@pytest.fixture
def fleet_key(tmp_path: Path) -> tuple[ec.EllipticCurvePrivateKey, Path]:
    private = ec.generate_private_key(ec.SECP256R1())
    public_jwk = json.loads(ECAlgorithm.to_jwk(private.public_key()))
    jwks = tmp_path / "fleet.jwks"
    jwks.write_text(json.dumps({"keys": [{**public_jwk, "kid": "fleet-1", "use": "sig"}]}))
    return private, jwks


def fleet_token(private: ec.EllipticCurvePrivateKey, sub: str, **claims: object) -> dict[str, str]:
    payload = {"sub": sub, "aud": "edgepos", "exp": time.time() + 300, **claims}
    return bearer(jwt.encode(payload, private, algorithm="ES256", headers={"kid": "fleet-1"}))


def test_a_fleet_signed_token_opens_its_own_vehicle_only(tmp_path, fleet_key):
    private, jwks = fleet_key
    with TestClient(create_app(make_settings(tmp_path, vehicle_auth="jwt", vehicle_jwks=jwks))) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        assert (
            create(client, "tram-3", fleet_token(private, "tram-3")).status_code == 201
        )  # no registry needed
        assert_error(create(client, "tram-4", fleet_token(private, "tram-3")), 403, "forbidden")
        stranger = ec.generate_private_key(ec.SECP256R1())
        refusals = [
            fleet_token(private, "tram-3", exp=time.time() - 3600),
            fleet_token(private, "tram-3", aud="someone-else"),
            fleet_token(stranger, "tram-3"),
            bearer(
                jwt.encode(
                    {"sub": "tram-3", "aud": "edgepos", "exp": time.time() + 60}, None, algorithm="none"
                )
            ),
        ]
        messages = {
            assert_error(create(client, "tram-3", credential), 401, "unauthorized")["message"]
            for credential in refusals
        }
        assert messages == {INVALID}
        assert create(client, "tram-3", ADMIN).status_code == 201
        assert_error(client.get("/v1/sessions", headers=fleet_token(private, "tram-3")), 403, "forbidden")


def test_a_key_set_that_does_not_parse_stops_the_start(tmp_path):
    broken = tmp_path / "broken.jwks"
    broken.write_text("{not json")
    with pytest.raises(JwksError, match="broken.jwks"):
        create_app(make_settings(tmp_path, vehicle_auth="jwt", vehicle_jwks=broken))
    environment = {
        **{k: v for k, v in os.environ.items() if not k.startswith("EDGEPOS_")},
        "EDGEPOS_VEHICLE_AUTH": "jwt",
        "EDGEPOS_VEHICLE_JWKS": str(broken),
        "EDGEPOS_ADMIN_KEY": "k" * 24,
    }
    finished = subprocess.run(
        [sys.executable, "-m", "edgepos.api.serve", "--port", "0"],
        check=False,  # the exit status is what the test asserts
        env=environment,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert finished.returncode == 2
    assert "EDGEPOS_VEHICLE_JWKS" in finished.stderr and "broken.jwks" in finished.stderr


# -- forgeries ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def forgery_target(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, str, str, str]]:
    """One app for every example: a registered vehicle's key and a live session's id and token. The
    failure budget is out of the way: this test is about what a forgery opens, not how often one may try."""
    settings = make_settings(
        tmp_path_factory.mktemp("forgery"), auth_failure_rate_per_s=1e6, auth_failure_burst=10**6
    )
    with TestClient(create_app(settings)) as client:
        key = register(client, "target")["Authorization"][len("Bearer ") :]
        created = create(client, "target", bearer(key)).json()
        yield client, key, created["session_id"], created["token"]


def _mutate(secret: str, data: st.DataObject) -> str:
    kind = data.draw(st.sampled_from(["flip", "truncate", "extend", "case", "replace_tail"]))
    if kind == "flip":
        at = data.draw(st.integers(0, len(secret) - 1))
        new = data.draw(
            st.characters(codec="ascii", exclude_characters="\r\n").filter(lambda c: c != secret[at])
        )
        return secret[:at] + new + secret[at + 1 :]
    if kind == "truncate":
        return secret[: data.draw(st.integers(0, len(secret) - 1))]
    if kind == "extend":
        return secret + data.draw(
            st.text(st.characters(codec="ascii", min_codepoint=33, max_codepoint=126), min_size=1, max_size=8)
        )
    if kind == "case":
        swapped = secret.swapcase()
        return swapped if swapped != secret else secret + "x"
    keep = data.draw(st.integers(0, len(secret) - 1))
    tail = data.draw(
        st.text(st.characters(codec="ascii", min_codepoint=33, max_codepoint=126), min_size=1, max_size=40)
    )
    forged = secret[:keep] + tail
    return forged if forged != secret else secret + "x"


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_forged_vehicle_keys_and_session_tokens_open_nothing(forgery_target, data):
    """Any change to a valid vehicle key or session token yields a credential that opens no session and
    reads nothing: answered 401 (403 for a valid token of another session), never 2xx."""
    client, key, session_id, token = forgery_target
    forged_key = _mutate(key, data)
    response = create(client, data.draw(st.sampled_from(["target", "other"])), bearer(forged_key))
    assert response.status_code in {401, 403}, (forged_key, response.text)
    assert response.status_code == 401 or forged_key == key
    forged_token = _mutate(token, data)
    read = client.get(f"/v1/sessions/{session_id}", headers=bearer(forged_token))
    assert read.status_code in {401, 403}, (forged_token, read.text)
    assert client.get("/v1/sessions", headers=ADMIN).json()["sessions"][0]["session_id"] == session_id
