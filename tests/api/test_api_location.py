"""The MEC 013 location adapter's queries (/location/v3/queries), the operator's zones (/v1/zones), the
read key, the 409 without a site origin and the adapter's RFC 7807 problem details."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from apihelp import ADMIN, assert_error, batch_body, bearer, make_settings, open_session
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from edgepos.geo import GeodeticOrigin
from fastapi.testclient import TestClient

ORIGIN = GeodeticOrigin.from_degrees(48.137, 11.575, 520.0)
READ_KEY = "read-key-0123456789abcdef0123456789abcdef"
READER = bearer(READ_KEY)
USERS = "/location/v3/queries/users"
DISTANCE = "/location/v3/queries/distance"


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return make_settings(
        tmp_path, origin_lat=48.137, origin_lon=11.575, origin_height=520.0, read_key=READ_KEY
    )


def drive(client: TestClient, vehicle_id: str, first: int, count: int) -> dict[str, Any]:
    """Open a session for the vehicle and apply one batch of the scenario's epochs; its last fix."""
    session_id, token = open_session(client, vehicle_id=vehicle_id)
    response = client.post(
        f"/v1/sessions/{session_id}/batches", json=batch_body(1, first, count), headers=token
    )
    assert response.status_code == 200, response.text
    fix: dict[str, Any] = response.json()["fixes"][-1]
    assert fix["status"] == "tracking"
    return fix


def assert_problem(response: Any, status: int, *words: str) -> dict[str, Any]:
    """An RFC 7807 problem details body with this status whose detail says each of ``words``."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    body: dict[str, Any] = response.json()
    assert set(body) == {"type", "title", "status", "detail", "instance"}
    assert body["status"] == status and body["instance"] == response.request.url.path
    for word in words:
        assert word in body["detail"], body["detail"]
    return body


def test_a_user_is_its_latest_fix_in_degrees_with_a_95_percent_circle(client: TestClient):
    fix = drive(client, "car-1", 0, 20)
    response = client.get(USERS, params={"address": "acr:car-1"}, headers=ADMIN)
    assert response.status_code == 200, response.text
    listing = response.json()["userList"]
    assert listing["resourceURL"].endswith("/location/v3/queries/users?address=acr%3Acar-1")
    [user] = listing["user"]
    assert user["address"] == "acr:car-1"
    assert user["resourceURL"] == "http://testserver/location/v3/queries/users?address=acr:car-1"
    info = user["locationInfo"]
    lat, lon, _ = ORIGIN.enu_to_geodetic(fix["x"], fix["y"])
    assert info["shape"] == 5
    assert info["latitude"] == [pytest.approx(math.degrees(lat), abs=1e-12)]
    assert info["longitude"] == [pytest.approx(math.degrees(lon), abs=1e-12)]
    assert "altitude" not in info  # rsu_imu estimates no height
    (xx, xy), (_, yy) = fix["position_covariance"]
    major = (xx + yy) / 2 + math.sqrt((xx - yy) ** 2 / 4 + xy * xy)
    assert info["accuracy"] == math.ceil(2.447746830680816 * math.sqrt(major))
    bearing = math.degrees(math.atan2(fix["vx"], fix["vy"])) % 360  # clockwise from north
    assert info["velocity"] == {
        "velocityType": 1,
        "bearing": round(bearing) % 360,
        "horizontalSpeed": round(math.hypot(fix["vx"], fix["vy"]) * 3.6),
    }
    assert 80 <= info["velocity"]["bearing"] <= 100  # the scenario's vehicle starts eastwards at ~36 km/h
    assert 30 <= info["velocity"]["horizontalSpeed"] <= 42
    assert info["timestamp"] == user["timeStamp"]
    assert set(user["timeStamp"]) == {"seconds", "nanoSeconds"}
    assert "zoneId" not in user


def test_user_filters(client: TestClient):
    drive(client, "car-1", 0, 20)  # near x = 10 m
    drive(client, "car-2", 0, 80)  # near x = 40 m
    everyone = client.get(USERS, headers=ADMIN).json()["userList"]["user"]
    assert [user["address"] for user in everyone] == ["acr:car-1", "acr:car-2"]
    assert (
        client.put(
            "/v1/zones/far", json={"circle": {"center": [40.0, 0.0], "radius": 5.0}}, headers=ADMIN
        ).status_code
        == 200
    )
    in_zone = client.get(USERS, params={"zoneId": "far"}, headers=ADMIN).json()["userList"]["user"]
    assert [(user["address"], user["zoneId"]) for user in in_zone] == [("acr:car-2", "far")]
    both = client.get(USERS, params=[("address", "acr:car-2"), ("address", "acr:nobody")], headers=ADMIN)
    assert [user["address"] for user in both.json()["userList"]["user"]] == ["acr:car-2"]
    assert_problem(client.get(USERS, params={"address": "acr:nobody"}, headers=ADMIN), 404, "acr:nobody")
    assert_problem(client.get(USERS, params={"address": "car-1"}, headers=ADMIN), 422, "address", "acr:")
    assert_problem(client.get(USERS, params={"zoneId": "nowhere"}, headers=ADMIN), 422, "zoneId", "nowhere")
    assert_problem(client.get(USERS, params={"accessPointId": "ap1"}, headers=ADMIN), 422, "accessPointId")
    zones = client.get("/location/v3/queries/zones", headers=ADMIN).json()["zoneList"]["zone"]
    assert [(zone["zoneId"], zone["numberOfUsers"], zone["numberOfAccessPoints"]) for zone in zones] == [
        ("far", 1, 0)
    ]
    one = client.get("/location/v3/queries/zones/far", headers=ADMIN).json()["zoneInfo"]
    assert one["resourceURL"] == "http://testserver/location/v3/queries/zones/far"
    assert_problem(client.get("/location/v3/queries/zones/near", headers=ADMIN), 404, "near")


def test_distance_between_vehicles_and_to_a_point(client: TestClient):
    first = drive(client, "car-1", 0, 20)
    second = drive(client, "car-2", 0, 80)
    response = client.get(
        DISTANCE, params=[("address", "acr:car-1"), ("address", "acr:car-2")], headers=ADMIN
    )
    assert response.status_code == 200, response.text
    distance = response.json()["terminalDistance"]
    assert distance["distance"] == round(math.hypot(first["x"] - second["x"], first["y"] - second["y"]))
    assert 25 <= distance["distance"] <= 35
    assert distance["accuracy"] >= 1 and set(distance["timestamp"]) == {"seconds", "nanoSeconds"}
    lat, lon, _ = ORIGIN.enu_to_geodetic(first["x"] + 100.0, first["y"])
    to_point = client.get(
        DISTANCE,
        params={"address": "acr:car-1", "latitude": math.degrees(lat), "longitude": math.degrees(lon)},
        headers=ADMIN,
    )
    assert to_point.json()["terminalDistance"]["distance"] == 100
    assert_problem(client.get(DISTANCE, params={"address": "acr:car-1"}, headers=ADMIN), 422, "address")
    assert_problem(
        client.get(DISTANCE, params={"address": "acr:car-1", "latitude": 48.1}, headers=ADMIN),
        422,
        "longitude",
    )
    assert_problem(
        client.get(DISTANCE, params={"address": "acr:car-1", "latitude": 91, "longitude": 0}, headers=ADMIN),
        422,
        "latitude",
    )
    missing = client.get(DISTANCE, params=[("address", "acr:car-1"), ("address", "acr:gone")], headers=ADMIN)
    assert_problem(missing, 404, "acr:gone")


def test_the_read_key_opens_the_adapter_and_the_fix_stream_only(client: TestClient):
    drive(client, "car-1", 0, 20)
    assert client.get(USERS, headers=READER).status_code == 200
    assert_problem(client.get(USERS), 401, "missing credentials")
    assert_problem(client.get(USERS, headers=bearer("wrong")), 401)
    _, token = open_session(client, vehicle_id="car-9")
    assert_problem(client.get(USERS, headers=token), 403, "read key")
    assert_error(client.get("/v1/zones", headers=READER), 403, "forbidden")
    assert_error(client.get("/v1/sessions", headers=READER), 403, "forbidden")
    assert_error(client.get("/v1/rsus", headers=READER), 403, "forbidden")
    session_id, _ = open_session(client, vehicle_id="car-8")
    assert_error(client.get(f"/v1/sessions/{session_id}", headers=READER), 403, "forbidden")
    # past authentication on the stream: its own parameter check answers (an SSE stream would never end)
    stream = client.get("/v1/stream/fixes", params={"pipeline": "nope"}, headers=READER)
    assert_error(stream, 422, "invalid_request")


def test_settings_refuse_a_weak_or_shared_read_key(tmp_path: Path):
    with pytest.raises(ValueError, match="at least 32"):
        make_settings(tmp_path, read_key="short")
    with pytest.raises(ValueError, match="differ from the admin key"):
        make_settings(tmp_path, admin_key="k" * 40, read_key="k" * 40)


def test_without_a_site_origin_the_adapter_answers_409(tmp_path: Path):
    with TestClient(create_app(make_settings(tmp_path, read_key=READ_KEY))) as client:
        for path in (USERS, DISTANCE, "/location/v3/queries/zones", "/location/v3/subscriptions/users"):
            assert_problem(client.get(path, headers=READER), 409, "EDGEPOS_ORIGIN_LAT")
        wgs84 = {"frame": "wgs84", "circle": {"center": [0.84, 0.2], "radius": 10.0}}
        assert_error(client.put("/v1/zones/a", json=wgs84, headers=ADMIN), 409, "conflict")
        site = {"circle": {"center": [0.0, 0.0], "radius": 10.0}}
        assert client.put("/v1/zones/a", json=site, headers=ADMIN).status_code == 200


def test_zones_in_the_site_frame_and_in_wgs84(client: TestClient):
    square = [[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0]]
    written = client.put("/v1/zones/square", json={"polygon": square}, headers=ADMIN)
    assert written.status_code == 200, written.text
    assert written.json()["site"] == {"circle": None, "polygon": square}
    corners = [list(ORIGIN.enu_to_geodetic(x, y)[:2]) for x, y in square]
    geodetic = client.put(
        "/v1/zones/square-wgs84", json={"frame": "wgs84", "polygon": corners}, headers=ADMIN
    )
    assert geodetic.status_code == 200, geodetic.text
    for got, want in zip(geodetic.json()["site"]["polygon"], square, strict=True):
        assert got == pytest.approx(want, abs=1e-6)
    assert geodetic.json()["polygon"] == corners
    listing = client.get("/v1/zones", headers=ADMIN).json()["zones"]
    assert [zone["zone_id"] for zone in listing] == ["square", "square-wgs84"]
    assert client.get("/v1/zones/square", headers=ADMIN).json()["frame"] == "site"
    assert client.delete("/v1/zones/square", headers=ADMIN).status_code == 204
    assert_error(client.get("/v1/zones/square", headers=ADMIN), 404, "not_found")
    assert_error(client.delete("/v1/zones/square", headers=ADMIN), 404, "not_found")


@pytest.mark.parametrize(
    ("body", "field"),
    [
        (
            {
                "circle": {"center": [0.0, 0.0], "radius": 5.0},
                "polygon": [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]],
            },
            "body",
        ),
        ({}, "body"),
        ({"polygon": [[0.0, 0.0], [10.0, 10.0], [10.0, 0.0], [0.0, 10.0]]}, "polygon"),
        ({"polygon": [[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]}, "polygon"),
        ({"polygon": [[0.0, 0.0], [1.0, 1.0]]}, "polygon"),
        ({"circle": {"center": [0.0, 0.0], "radius": 0.0}}, "circle.radius"),
        ({"circle": {"center": [0.0], "radius": 1.0}}, "circle.center"),
        ({"frame": "wgs84", "circle": {"center": [2.0, 0.0], "radius": 1.0}}, "circle.center"),
        ({"frame": "ecef", "circle": {"center": [0.0, 0.0], "radius": 1.0}}, "frame"),
    ],
)
def test_bad_zones_are_422_naming_the_field(client: TestClient, body: dict[str, Any], field: str):
    error = assert_error(client.put("/v1/zones/z", json=body, headers=ADMIN), 422, "invalid_request")
    assert [problem["field"] for problem in error["problems"]] == [field]


def test_openapi_documents_the_adapter(client: TestClient):
    document = client.get("/openapi.json").json()
    velocity = document["components"]["schemas"]["Velocity"]["properties"]["bearing"]
    assert "Degrees" in velocity["description"] and "exception" in velocity["description"]
    problem = document["paths"]["/location/v3/queries/users"]["get"]["responses"]["422"]
    assert "application/problem+json" in problem["content"]
    assert set(document["paths"]["/location/v3/subscriptions/zones/{subscriptionId}"]) == {"get", "delete"}
