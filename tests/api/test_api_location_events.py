"""MEC 013 location subscriptions: their resources, the callback checks, notifications POSTed to a real
receiver on 127.0.0.1 when a simulated vehicle enters and leaves a zone, retries with backoff, expiry
after failed deliveries, and one notifier per site when two apps (workers) share a store."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from apihelp import ADMIN, batch_body, make_settings, open_session, rsu_payload
from callbackhelp import receiver
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from fastapi.testclient import TestClient
from test_api_location import READER, assert_problem

USER_SUBS = "/location/v3/subscriptions/users"
ZONE_SUBS = "/location/v3/subscriptions/zones"
GATE = {"circle": {"center": [90.0, 0.0], "radius": 15.0}}
"""The scenario's vehicle starts at (0, 0) eastwards: about x = 10 m after epoch 20, 90 m after epoch 150
and 248 m after epoch 300 (its truth), so it enters this zone in the second batch and leaves it in the third."""
LOCATION = {"origin_lat": 48.137, "origin_lon": 11.575, "location_poll_s": 0.05}


@pytest.fixture
def settings_overrides() -> dict[str, Any]:
    """Settings a test changes from this module's (parametrize it to change them)."""
    return {}


@pytest.fixture
def settings(tmp_path: Path, settings_overrides: dict[str, Any]) -> Settings:
    options: dict[str, Any] = {"callback_backoff_s": 0.2, "callback_max_failures": 3, **settings_overrides}
    return make_settings(
        tmp_path, **LOCATION, read_key="read-key-0123456789abcdef0123456789abcdef", **options
    )


def user_subscription(callback: str, **extra: Any) -> dict[str, Any]:
    return {
        "subscriptionType": "UserLocationEventSubscription",
        "address": "acr:car-1",
        "callbackReference": callback,
        **extra,
    }


def zone_subscription(callback: str, **extra: Any) -> dict[str, Any]:
    return {
        "subscriptionType": "ZoneLocationEventSubscription",
        "zoneId": "gate",
        "callbackReference": callback,
        **extra,
    }


class Vehicle:
    """car-1 driving the scenario batch by batch."""

    def __init__(self, client: TestClient) -> None:
        self.client = client
        self.session_id, self.token = open_session(client, vehicle_id="car-1")
        self.seq, self.epoch = 0, 0

    def drive_to(self, epoch: int) -> dict[str, Any]:
        self.seq += 1
        body = batch_body(self.seq, self.epoch, epoch - self.epoch)
        response = self.client.post(f"/v1/sessions/{self.session_id}/batches", json=body, headers=self.token)
        assert response.status_code == 200, response.text
        self.epoch = epoch
        fix: dict[str, Any] = response.json()["fixes"][-1]
        return fix


def test_subscription_resources(client: TestClient):
    assert client.put("/v1/zones/gate", json=GATE, headers=ADMIN).status_code == 200
    callback = "http://127.0.0.1:9/notify"
    created = client.post(USER_SUBS, json=user_subscription(callback, clientCorrelator="c-7"), headers=READER)
    assert created.status_code == 201, created.text
    body = created.json()
    href = body["_links"]["self"]["href"]
    assert created.headers["location"] == href
    assert href.startswith("http://testserver/location/v3/subscriptions/users/")
    assert body == {
        "_links": {"self": {"href": href}},
        "subscriptionType": "UserLocationEventSubscription",
        "address": "acr:car-1",
        "callbackReference": callback,
        "clientCorrelator": "c-7",
        "eventType": ["ENTERING_AREA_EVENT", "LEAVING_AREA_EVENT"],
    }
    path = href.removeprefix("http://testserver")
    assert client.get(path, headers=READER).json() == body
    zone = client.post(
        ZONE_SUBS, json=zone_subscription(callback, locationEventType=["LEAVING_AREA_EVENT"]), headers=ADMIN
    )
    assert zone.status_code == 201, zone.text
    assert zone.json()["locationEventType"] == ["LEAVING_AREA_EVENT"] and zone.json()["zoneId"] == "gate"
    listing = client.get(USER_SUBS, headers=READER).json()
    assert listing["subscription"] == [{"href": href, "subscriptionType": "UserLocationEventSubscription"}]
    assert (
        client.get(USER_SUBS, params={"subscription_type": "periodic"}, headers=READER).json()["subscription"]
        == []
    )
    assert client.get(USER_SUBS, params={"address": "acr:car-2"}, headers=READER).json()["subscription"] == []
    assert len(client.get(ZONE_SUBS, params={"zoneId": "gate"}, headers=READER).json()["subscription"]) == 1
    assert_problem(
        client.get(USER_SUBS, params={"subscription_type": "sometimes"}, headers=READER),
        422,
        "subscription_type",
    )
    zone_path = zone.headers["location"].removeprefix("http://testserver")
    assert_problem(
        client.get(zone_path.replace("/zones/", "/users/"), headers=READER), 404
    )  # not a user subscription
    deleted = client.delete("/v1/zones/gate", headers=ADMIN)
    assert deleted.status_code == 409 and "zone subscription" in deleted.json()["error"]["message"]
    assert client.delete(path, headers=READER).status_code == 204
    assert_problem(client.get(path, headers=READER), 404)
    assert_problem(client.delete(path, headers=READER), 404)
    assert client.delete(zone_path, headers=READER).status_code == 204
    assert client.delete("/v1/zones/gate", headers=ADMIN).status_code == 204
    assert_problem(client.get(USER_SUBS + "/not-an-id", headers=READER), 422, "subscriptionId")


@pytest.mark.parametrize(
    ("callback", "words"),
    [
        ("ftp://127.0.0.1/notify", ("callbackReference", "http")),
        ("127.0.0.1:8080/notify", ("callbackReference", "http")),
        ("http://example.com/notify", ("callbackReference", "example.com", "EDGEPOS_CALLBACK_HOSTS")),
        ("http://10.0.0.8:8080/notify", ("callbackReference", "10.0.0.8")),
        ("http://user:pw@127.0.0.1/notify", ("callbackReference", "password")),
        ("http://127.0.0.1:99999/notify", ("callbackReference", "Port")),
    ],
)
def test_a_callback_must_be_http_on_an_allowed_host(
    client: TestClient, callback: str, words: tuple[str, ...]
):
    assert_problem(client.post(USER_SUBS, json=user_subscription(callback), headers=READER), 422, *words)


def test_bad_subscriptions_are_422(client: TestClient):
    ok = "http://localhost:9/notify"
    assert client.put("/v1/zones/gate", json=GATE, headers=ADMIN).status_code == 200
    cases = [
        (
            USER_SUBS,
            {**user_subscription(ok), "subscriptionType": "UserLocationPeriodicSubscription"},
            "subscriptionType",
        ),
        (USER_SUBS, user_subscription(ok, address="car-1"), "address"),
        (USER_SUBS, user_subscription(ok, eventType=["ARRIVED"]), "eventType"),
        (USER_SUBS, user_subscription(ok, websockNotifConfig={}), "websockNotifConfig"),
        (
            USER_SUBS,
            user_subscription(ok, expiryDeadline={"seconds": 1000, "nanoSeconds": 0}),
            "expiryDeadline",
        ),
        (ZONE_SUBS, zone_subscription(ok, zoneId="elsewhere"), "zoneId"),
        (ZONE_SUBS, zone_subscription(ok, addressList=["car-1"]), "addressList"),
    ]
    for path, body, field in cases:
        assert_problem(client.post(path, json=body, headers=READER), 422, field)
    assert_problem(
        client.post(USER_SUBS, content=b"{", headers={**READER, "Content-Type": "application/json"}),
        422,
        "body",
    )


def test_more_callback_hosts_can_be_allowed(tmp_path: Path):
    settings = make_settings(tmp_path, **LOCATION, callback_hosts="apps.example.net, 192.0.2.7")
    with TestClient(create_app(settings)) as client:
        for callback in ("https://apps.example.net/cb", "http://192.0.2.7:8080/cb"):
            assert client.post(USER_SUBS, json=user_subscription(callback), headers=ADMIN).status_code == 201
        assert_problem(
            client.post(USER_SUBS, json=user_subscription("http://127.0.0.1/cb"), headers=ADMIN),
            422,
            "127.0.0.1",
        )


def test_entering_and_leaving_a_zone_is_notified_to_a_real_receiver(client: TestClient):
    assert client.put("/v1/zones/gate", json=GATE, headers=ADMIN).status_code == 200
    vehicle = Vehicle(client)
    vehicle.drive_to(20)
    with receiver() as sink:
        user = client.post(USER_SUBS, json=user_subscription(sink.url), headers=READER).json()
        zone = client.post(
            ZONE_SUBS, json=zone_subscription(sink.url, addressList=["acr:car-1"]), headers=READER
        ).json()
        time.sleep(0.3)  # several polls: nothing has crossed yet
        assert sink.received() == []
        inside = vehicle.drive_to(150)
        assert 75 <= inside["x"] <= 105
        entered = sink.wait_for(lambda bodies: len(bodies) >= 2)
        by_type = {body["notificationType"]: body for body in entered}
        user_note = by_type["UserLocationEventNotification"]
        assert user_note["address"] == "acr:car-1" and user_note["zoneId"] == "gate"
        assert user_note["eventType"] == "ENTERING_AREA_EVENT"
        assert user_note["_links"] == {"subscription": {"href": user["_links"]["self"]["href"]}}
        assert user_note["locationInfo"]["shape"] == 5 and len(user_note["locationInfo"]["latitude"]) == 1
        zone_note = by_type["ZoneLocationEventNotification"]
        assert zone_note["userLocationEvent"] == "ENTERING_AREA_EVENT" and zone_note["zoneId"] == "gate"
        assert zone_note["_links"] == {"subscription": {"href": zone["_links"]["self"]["href"]}}
        assert set(zone_note["timeStamp"]) == {"seconds", "nanoSeconds"}
        users = client.get("/location/v3/queries/users", headers=READER).json()["userList"]["user"]
        assert users[0]["zoneId"] == "gate"
        vehicle.drive_to(300)
        left = sink.wait_for(lambda bodies: len(bodies) >= 4)[2:]
        assert sorted(body.get("eventType") or body.get("userLocationEvent") for body in left) == [
            "LEAVING_AREA_EVENT",
            "LEAVING_AREA_EVENT",
        ]
        time.sleep(0.3)
        assert len(sink.received()) == 4  # each crossing once


def test_a_failing_callback_is_retried_with_backoff_then_the_subscription_expires(client: TestClient):
    assert client.put("/v1/zones/gate", json=GATE, headers=ADMIN).status_code == 200
    vehicle = Vehicle(client)
    vehicle.drive_to(20)
    with receiver() as sink:
        sink.status = 500
        created = client.post(ZONE_SUBS, json=zone_subscription(sink.url), headers=ADMIN)
        path = created.headers["location"].removeprefix("http://testserver")
        vehicle.drive_to(150)
        sink.wait_for(lambda bodies: len(bodies) >= 3)  # callback_max_failures = 3
        deadline = time.monotonic() + 10
        while client.get(path, headers=ADMIN).status_code != 404 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert_problem(client.get(path, headers=ADMIN), 404)
        gaps = [later - earlier for earlier, later in zip(sink.times, sink.times[1:], strict=False)]
        assert len(sink.received()) == 3
        assert all(body["userLocationEvent"] == "ENTERING_AREA_EVENT" for body in sink.received())
        assert gaps[0] >= 0.2 - 0.02 and gaps[1] >= 0.4 - 0.02  # callback_backoff_s, then doubled
        vehicle.drive_to(300)
        time.sleep(0.3)
        assert len(sink.received()) == 3  # expired: nothing more


@pytest.mark.parametrize("settings_overrides", [{"callback_max_failures": 8}])
def test_a_callback_that_recovers_gets_every_pending_notification_in_order(client: TestClient):
    # Eight failures (0.2 s doubling: about 25 s) outlast the leaving batch, however long it takes: the
    # scheduler may start its heavy lane's worker process for it (about 2 s on the 2-core box), during which
    # three failures (1.4 s) would expire the subscription before the callback recovers.
    assert client.put("/v1/zones/gate", json=GATE, headers=ADMIN).status_code == 200
    vehicle = Vehicle(client)
    vehicle.drive_to(20)
    with receiver() as sink:
        sink.status = 503
        client.post(ZONE_SUBS, json=zone_subscription(sink.url), headers=ADMIN)
        vehicle.drive_to(150)
        sink.wait_for(lambda bodies: len(bodies) >= 1)
        vehicle.drive_to(300)  # leaves while the entry is still undelivered
        sink.status = 204
        sink.wait_for(lambda bodies: any(b["userLocationEvent"] == "LEAVING_AREA_EVENT" for b in bodies))
        delivered = [body["userLocationEvent"] for body in sink.answered_with(204)]
        assert delivered == ["ENTERING_AREA_EVENT", "LEAVING_AREA_EVENT"]
        # every failed try was the entry: the leaving waited behind it
        assert {body["userLocationEvent"] for body in sink.answered_with(503)} == {"ENTERING_AREA_EVENT"}


def test_two_workers_sharing_a_store_send_each_notification_once(tmp_path: Path):
    settings = make_settings(tmp_path, **LOCATION, store=f"sqlite:///{tmp_path / 'site.db'}")
    with (
        TestClient(create_app(settings)) as first,
        TestClient(create_app(settings)) as second,
        receiver() as sink,
    ):
        assert first.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
        assert first.put("/v1/zones/gate", json=GATE, headers=ADMIN).status_code == 200
        vehicle = Vehicle(second)
        vehicle.drive_to(20)
        assert first.post(ZONE_SUBS, json=zone_subscription(sink.url), headers=ADMIN).status_code == 201
        vehicle.drive_to(150)
        sink.wait_for(lambda bodies: len(bodies) >= 1)
        vehicle.drive_to(300)
        sink.wait_for(lambda bodies: len(bodies) >= 2)
        time.sleep(0.5)  # ten polls of each worker
        assert [body["userLocationEvent"] for body in sink.received()] == [
            "ENTERING_AREA_EVENT",
            "LEAVING_AREA_EVENT",
        ]


def test_a_subscription_ends_at_its_expiry_deadline(client: TestClient):
    deadline = time.time() + 3.0  # the creation must land before it on a loaded machine (seen late at 0.5 s)
    seconds = int(deadline)
    body = user_subscription(
        "http://127.0.0.1:9/notify",
        expiryDeadline={"seconds": seconds, "nanoSeconds": int((deadline - seconds) * 1e9)},
    )
    created = client.post(USER_SUBS, json=body, headers=READER)
    assert created.status_code == 201, created.text
    assert created.json()["expiryDeadline"] == body["expiryDeadline"]
    path = created.headers["location"].removeprefix("http://testserver")
    assert client.get(path, headers=READER).status_code == 200
    finish = time.monotonic() + 10.0
    while client.get(path, headers=READER).status_code == 200 and time.monotonic() < finish:
        time.sleep(0.05)
    assert time.time() >= deadline
    assert_problem(client.get(path, headers=READER), 404)


def test_a_body_refused_before_routing_is_problem_details_too(client: TestClient):
    huge = user_subscription("http://127.0.0.1:9/notify", clientCorrelator="x" * 2_000_000)
    assert_problem(client.post(USER_SUBS, json=huge, headers=READER), 413, "EDGEPOS_MAX_BODY_BYTES")
    assert client.post("/v1/sessions", json={"vehicle_id": "x" * 2_000_000}, headers=ADMIN).json()["error"][
        "code"
    ] == ("payload_too_large")
