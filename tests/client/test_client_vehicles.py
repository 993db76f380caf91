"""The vehicle registry, vehicle credentials, one live session per vehicle and the session listing, through
both clients against the real app in-process: the blocking client through Starlette's TestClient, the
async one through httpx.ASGITransport. Vehicle ids with '/' and a space travel percent-encoded in the path
and come back whole."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import jwt
import pytest
from clienthelp import ADMIN_KEY, INITIAL_STATE, TestClientTransport, batch, make_app, scenario_rsus
from cryptography.hazmat.primitives.asymmetric import ec
from edgepos.api import schemas, vehicle_schemas
from edgepos_client import (
    AsyncEdgeposClient,
    Conflict,
    EdgeposClient,
    Forbidden,
    NotFound,
    Session,
    Superseded,
    TransportError,
    Unauthorized,
    VehicleImport,
)
from edgepos_client import _protocol as protocol
from edgepos_client._protocol import Retry
from fastapi import FastAPI
from fastapi.testclient import TestClient
from jwt.algorithms import ECAlgorithm

URL = "http://edgepos.test"
ODD = "fleet/7 bus"  # a '/' and a space: both percent-encoded in a path segment
TRICKY = ("depot:3@north+x", "a/key", "b/key/key", "  spaced  out  ")


class Recording(httpx.BaseTransport):
    """Passes every request on and keeps (method, raw path) of each."""

    def __init__(self, inner: httpx.BaseTransport) -> None:
        self.inner = inner
        self.sent: list[tuple[str, str]] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.sent.append((request.method, request.url.raw_path.decode()))
        return self.inner.handle_request(request)


@pytest.fixture
def app(tmp_path: Path) -> FastAPI:
    return make_app(tmp_path)


@pytest.fixture
def transport(app: FastAPI) -> Iterator[Recording]:
    with TestClient(app) as test_client:
        yield Recording(TestClientTransport(test_client))


@pytest.fixture
def admin(transport: Recording) -> Iterator[EdgeposClient]:
    with EdgeposClient(URL, ADMIN_KEY, transport=transport, backoff=0.0) as client:
        client.put_rsus(scenario_rsus())
        yield client


def vehicle(transport: httpx.BaseTransport, key: str) -> EdgeposClient:
    return EdgeposClient(URL, vehicle_key=key, transport=transport, backoff=0.0)


# -- blocking client, in-process --------------------------------------------------------------------
def test_registry_round_trip_with_slashes_and_spaces(admin: EdgeposClient, transport: Recording) -> None:
    issued = {vehicle_id: admin.register_vehicle(vehicle_id) for vehicle_id in (ODD, *TRICKY)}
    for vehicle_id, key in issued.items():
        assert key.vehicle_id == vehicle_id and key.key.startswith("evk_")
        assert key.created_at == key.key_issued_at
        assert key.key not in repr(key)  # a key is shown once, not in logs of reprs
        read = admin.get_vehicle(vehicle_id)
        assert (read.vehicle_id, read.created_at) == (vehicle_id, key.created_at)
        assert read.key_issued_at == key.created_at
    assert len({key.key for key in issued.values()}) == len(issued)
    assert ("GET", "/v1/vehicles/fleet%2F7%20bus") in transport.sent

    rotated = admin.rotate_vehicle_key("a/key")  # POST /v1/vehicles/a%2Fkey/key: the id is "a/key"
    assert rotated.vehicle_id == "a/key" and rotated.key != issued["a/key"].key
    assert rotated.created_at == issued["a/key"].created_at <= rotated.key_issued_at
    assert admin.get_vehicle("b/key/key").vehicle_id == "b/key/key"
    page = admin.list_vehicles()
    assert [v.vehicle_id for v in page.vehicles] == sorted(issued) and page.total == len(issued)
    assert page.next_after is None

    with pytest.raises(Conflict) as again:
        admin.register_vehicle(ODD)
    assert type(again.value) is Conflict and again.value.status == 409 and ODD in again.value.message
    revoked = admin.revoke_vehicle("a/key")
    assert (revoked.vehicle_id, revoked.ended_session) == ("a/key", None)
    with pytest.raises(NotFound):
        admin.get_vehicle("a/key")
    with pytest.raises(NotFound):
        admin.revoke_vehicle("a/key")
    with pytest.raises(NotFound):
        admin.rotate_vehicle_key("never-registered")
    assert admin.get_vehicle("b/key/key").vehicle_id == "b/key/key"  # its neighbour in the path is intact
    sent = len(transport.sent)
    with pytest.raises(ValueError, match="characters '#'"):
        admin.register_vehicle("bus#1")
    assert len(transport.sent) == sent  # refused before sending


def test_vehicle_key_opens_its_own_vehicle_only(admin: EdgeposClient, transport: Recording) -> None:
    key = admin.register_vehicle(ODD).key
    with vehicle(transport, key) as car:
        session = car.create_session(ODD, initial_state=INITIAL_STATE)
        assert session.vehicle_id == ODD and session.superseded is None
        assert len(car.send_batch(session, batch(0, 3))) == 3
        with pytest.raises(Forbidden) as other:
            car.create_session("someone-else")
        assert other.value.status == 403 and "someone-else" in other.value.message
    with EdgeposClient(URL, key, transport=transport) as misused, pytest.raises(Forbidden):
        misused.list_vehicles()  # a vehicle key given as admin key opens no admin call

    new_key = admin.rotate_vehicle_key(ODD).key
    with vehicle(transport, key) as old, pytest.raises(Unauthorized):
        old.create_session(ODD)  # the rotated key opens nothing
    assert admin.get_session(session.session_id).last_seq == 1  # its session kept running
    with vehicle(transport, new_key) as car:
        newer = car.create_session(ODD, initial_state=INITIAL_STATE)
    assert newer.superseded == session.session_id

    revoked = admin.revoke_vehicle(ODD)
    assert revoked.ended_session == newer.session_id
    with vehicle(transport, new_key) as car, pytest.raises(Unauthorized) as gone:
        car.create_session(ODD)
    assert gone.value.status == 401
    with pytest.raises(NotFound):
        admin.get_session(newer.session_id)  # the revocation ended it


def test_no_vehicle_credential_means_the_admin_key(transport: Recording) -> None:
    with EdgeposClient(URL, transport=transport) as nobody, pytest.raises(Unauthorized):
        nobody.create_session("car-1")
    with EdgeposClient(URL, ADMIN_KEY, transport=transport) as admin:
        assert admin.create_session("car-1").vehicle_id == "car-1"  # the admin key opens any vehicle


def test_a_newer_session_supersedes_the_older(admin: EdgeposClient) -> None:
    first = admin.create_session(ODD, initial_state=INITIAL_STATE)
    admin.send_batch(first, batch(0, 2))
    second = admin.create_session(ODD, initial_state=INITIAL_STATE)
    assert second.superseded == first.session_id and first.superseded is None
    with pytest.raises(Superseded) as caught:
        admin.send_batch(first, batch(2, 2))
    error = caught.value
    assert isinstance(error, Conflict) and (error.status, error.code) == (409, "superseded")
    assert first.session_id in error.message and second.session_id in error.message
    assert first.last_seq == 1  # the refused batch did not advance the old handle
    with pytest.raises(Superseded):
        admin.get_session(first)  # with the old token
    assert len(admin.send_batch(second, batch(0, 2))) == 2
    other = admin.create_session("another car")
    assert other.superseded is None  # other vehicles are not affected


def test_import_in_chunks_and_page_through(admin: EdgeposClient, transport: Recording) -> None:
    ids = [f"fleet 9/{n:05d}" for n in range(protocol.MAX_VEHICLES_PER_IMPORT + 3)]
    before = [admin.register_vehicle(vehicle_id).key for vehicle_id in (ids[1], ids[-1])]
    sent = len(transport.sent)
    result = admin.import_vehicles(iter(ids))  # any iterable
    assert isinstance(result, VehicleImport)
    assert transport.sent[sent:] == [("POST", "/v1/vehicles/bulk")] * 2  # 5,000 + 3
    assert result.already_registered == [ids[1], ids[-1]]
    assert [key.vehicle_id for key in result.registered] == [i for i in ids if i not in (ids[1], ids[-1])]
    keys = {key.key for key in result.registered}
    assert len(keys) == len(ids) - 2 and all(key.startswith("evk_") for key in keys)
    assert not keys & set(before)

    again = admin.import_vehicles(ids[:10])
    assert again.registered == [] and again.already_registered == ids[:10]

    first = admin.list_vehicles(limit=1000)
    assert len(first.vehicles) == 1000 and first.total == len(ids)
    assert first.next_after == first.vehicles[-1].vehicle_id == ids[999]
    second = admin.list_vehicles(after=first.next_after, limit=1000)
    assert second.vehicles[0].vehicle_id == ids[1000]
    assert "/v1/vehicles?after=fleet%209%2F00999&limit=1000" in {path for _, path in transport.sent}
    sent = len(transport.sent)
    listed = [v.vehicle_id for v in admin.iter_vehicles(limit=1000)]
    assert listed == sorted(ids) and len(transport.sent) - sent == 6  # 5,003 in pages of 1,000


def test_listing_sessions(admin: EdgeposClient, transport: Recording) -> None:
    vehicles = [f"bus {n}/x" for n in range(5)]
    sessions = {v: admin.create_session(v, initial_state=INITIAL_STATE) for v in vehicles}
    gnss = admin.create_session("gnss car", "gnss_tight")
    admin.send_batch(sessions[vehicles[0]], batch(0, 3))

    everything: list[str] = []
    after: str | None = None
    pages = 0
    while True:
        page = admin.list_sessions(after=after, limit=2)
        pages += 1
        assert len(page.sessions) <= 2
        everything += [s.session_id for s in page.sessions]
        if page.next_after is None:
            break
        after = page.next_after
    assert pages == 3 and everything == sorted([s.session_id for s in sessions.values()] + [gnss.session_id])

    only = admin.list_sessions(vehicle_id=vehicles[0])
    assert [s.session_id for s in only.sessions] == [sessions[vehicles[0]].session_id]
    item = only.sessions[0]
    assert (item.vehicle_id, item.pipeline, item.last_seq, item.batches, item.epochs) == (
        vehicles[0],
        "rsu_imu",
        1,
        1,
        3,
    )
    assert item.status in ("initialised", "tracking") and item.last_fix_t == pytest.approx(0.15)
    assert item.created_at <= item.updated_at
    fresh = admin.list_sessions(vehicle_id=vehicles[1]).sessions[0]
    assert (fresh.status, fresh.last_fix_t, fresh.last_seq) == ("new", None, 0)
    by_pipeline = admin.list_sessions(pipeline="gnss_tight")
    assert [s.vehicle_id for s in by_pipeline.sessions] == ["gnss car"]
    assert admin.list_sessions(vehicle_id="nobody").sessions == []
    queries = [path for _, path in transport.sent if path.startswith("/v1/sessions?")]
    assert any("vehicle_id=bus%200%2Fx" in path for path in queries)

    holder = EdgeposClient(URL, sessions[vehicles[0]].token, transport=transport)
    with holder, pytest.raises(Forbidden):
        holder.list_sessions()  # a session token is not the admin key


# -- async client, in-process ----------------------------------------------------------------------
@pytest.fixture
def atransport(tmp_path: Path) -> httpx.ASGITransport:
    return httpx.ASGITransport(app=make_app(tmp_path))


@pytest.mark.anyio
async def test_async_registry_vehicle_key_and_supersession(atransport: httpx.ASGITransport) -> None:
    async with AsyncEdgeposClient(URL, ADMIN_KEY, transport=atransport, backoff=0.0) as admin:
        await admin.put_rsus(scenario_rsus())
        issued = await admin.register_vehicle(ODD)
        assert issued.vehicle_id == ODD and issued.key.startswith("evk_")
        assert (await admin.get_vehicle(ODD)).vehicle_id == ODD
        async with AsyncEdgeposClient(URL, vehicle_key=issued.key, transport=atransport) as car:
            first = await car.create_session(ODD, initial_state=INITIAL_STATE)
            assert first.superseded is None
            await car.send_batch(first, batch(0, 2))
            with pytest.raises(Forbidden):
                await car.create_session("b/key/key")
            second = await car.create_session(ODD, initial_state=INITIAL_STATE)
            assert second.superseded == first.session_id
            with pytest.raises(Superseded) as caught:
                await car.send_batch(first, batch(2, 2))
            assert caught.value.code == "superseded" and caught.value.status == 409
            assert len(await car.send_batch(second, batch(0, 2))) == 2

            listed = await admin.list_sessions(vehicle_id=ODD)
            assert [s.session_id for s in listed.sessions] == [second.session_id]
            assert listed.next_after is None

            rotated = await admin.rotate_vehicle_key(ODD)
            assert rotated.key != issued.key and rotated.vehicle_id == ODD
            with pytest.raises(Unauthorized):
                await car.create_session(ODD)  # the old key
            async with AsyncEdgeposClient(URL, vehicle_key=rotated.key, transport=atransport) as renewed:
                third = await renewed.create_session(ODD)
                assert third.superseded == second.session_id
                revoked = await admin.revoke_vehicle(ODD)
                assert (revoked.vehicle_id, revoked.ended_session) == (ODD, third.session_id)
                with pytest.raises(Unauthorized):
                    await renewed.create_session(ODD)
            with pytest.raises(NotFound):
                await admin.get_vehicle(ODD)
            assert (await admin.list_sessions(vehicle_id=ODD)).sessions == []


@pytest.mark.anyio
async def test_async_import_in_chunks_and_iterate(
    atransport: httpx.ASGITransport, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(protocol, "MAX_VEHICLES_PER_IMPORT", 40)  # 3 chunks of 40, 40, 20
    ids = [f"depot 2/{n:03d}" for n in range(100)]
    async with AsyncEdgeposClient(URL, ADMIN_KEY, transport=atransport) as admin:
        await admin.register_vehicle(ids[50])
        chunks = [chunk async for chunk in admin.import_vehicle_chunks(ids)]
        assert [len(c.registered) + len(c.already_registered) for c in chunks] == [40, 40, 20]
        assert chunks[1].already_registered == [ids[50]]
        again = await admin.import_vehicles(reversed(ids))
        assert again.registered == [] and again.already_registered == ids[::-1]
        page = await admin.list_vehicles(limit=30)
        assert page.total == 100 and page.next_after == ids[29]
        assert [v.vehicle_id async for v in admin.iter_vehicles(limit=30)] == ids
        with pytest.raises(ValueError, match="listed twice"):
            await admin.import_vehicles([ids[0], "new-one", ids[0]])
        with pytest.raises(NotFound):
            await admin.get_vehicle("new-one")  # nothing was sent


def _signed_token(private: ec.EllipticCurvePrivateKey, vehicle_id: str) -> str:
    now = int(time.time())
    claims = {"sub": vehicle_id, "aud": "edgepos", "iat": now, "exp": now + 300}
    return jwt.encode(claims, private, algorithm="ES256", headers={"kid": "fleet-1"})


@pytest.mark.anyio
async def test_async_vehicle_token_from_the_fleet_operator(tmp_path: Path) -> None:
    private = ec.generate_private_key(ec.SECP256R1())
    jwks = tmp_path / "fleet.jwks"
    public = {**json.loads(ECAlgorithm.to_jwk(private.public_key())), "kid": "fleet-1"}
    jwks.write_text(json.dumps({"keys": [public]}))
    transport = httpx.ASGITransport(app=make_app(tmp_path, vehicle_auth="jwt", vehicle_jwks=jwks))
    token = _signed_token(private, ODD)
    async with AsyncEdgeposClient(URL, vehicle_token=token, transport=transport) as car:
        session = await car.create_session(ODD)
        assert session.vehicle_id == ODD
        with pytest.raises(Forbidden):
            await car.create_session("someone-else")
    forged = _signed_token(ec.generate_private_key(ec.SECP256R1()), ODD)
    async with AsyncEdgeposClient(URL, vehicle_token=forged, transport=transport) as impostor:
        with pytest.raises(Unauthorized):
            await impostor.create_session(ODD)


# -- without a server ------------------------------------------------------------------------------
def test_one_vehicle_credential_at_most() -> None:
    with pytest.raises(ValueError, match="not both"):
        EdgeposClient(URL, vehicle_key="evk_a", vehicle_token="a.b.c")
    with pytest.raises(ValueError, match="not both"):
        AsyncEdgeposClient(URL, vehicle_key="evk_a", vehicle_token="a.b.c")
    with pytest.raises(ValueError, match="empty"):
        EdgeposClient(URL, vehicle_key="")


def test_bearer_of_each_call() -> None:
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        if request.url.path == "/v1/pipelines":
            return httpx.Response(200, json={"pipelines": []})
        created = {"session_id": "s", "token": "s.t", "vehicle_id": "v", "pipeline": "rsu_imu"}
        created["created_at"] = 1.0
        return httpx.Response(201, json=created)

    mock = httpx.MockTransport(handler)
    with EdgeposClient(URL, "admin", vehicle_key="evk_car", transport=mock) as client:
        client.create_session("v")
        client.pipelines()
    with EdgeposClient(URL, "admin", vehicle_token="h.p.s", transport=mock) as client:
        client.create_session("v")
    with EdgeposClient(URL, "admin", transport=mock) as client:
        client.create_session("v")
    assert [r.headers["authorization"] for r in seen] == [
        "Bearer evk_car",
        "Bearer admin",
        "Bearer h.p.s",
        "Bearer admin",
    ]


def test_retry_policy_of_the_new_calls() -> None:
    calls = protocol.Calls("admin")
    assert calls.register_vehicle("v").retry is Retry.CONNECT
    assert calls.import_vehicles(["v"]).retry is Retry.CONNECT
    assert calls.rotate_vehicle_key("v").retry is Retry.CONNECT
    assert calls.revoke_vehicle("v").retry is Retry.CONNECT
    assert calls.list_vehicles(None, 100).retry is Retry.ALWAYS
    assert calls.get_vehicle("v").retry is Retry.ALWAYS
    assert calls.list_sessions(None, 100, None, None).retry is Retry.ALWAYS

    attempts: list[str] = []

    def times_out_once(request: httpx.Request) -> httpx.Response:
        attempts.append(request.url.path)
        if attempts.count(request.url.path) == 1:
            raise httpx.ReadTimeout("reply lost", request=request)
        return httpx.Response(200, json={"vehicles": [], "total": 0, "next_after": None})

    with EdgeposClient(URL, "admin", transport=httpx.MockTransport(times_out_once), backoff=0.0) as client:
        assert client.list_vehicles().total == 0  # read again after a lost reply
        with pytest.raises(TransportError):
            client.rotate_vehicle_key("v")  # the lost reply may have carried the only copy of the key
    assert attempts == ["/v1/vehicles", "/v1/vehicles", "/v1/vehicles/v/key"]


def test_imports_are_checked_before_sending() -> None:
    sent: list[httpx.Request] = []
    mock = httpx.MockTransport(lambda request: sent.append(request) or httpx.Response(500))
    with EdgeposClient(URL, "admin", transport=mock) as client:
        with pytest.raises(ValueError, match=r"vehicle_ids\[2\].*listed twice"):
            client.import_vehicles(["a", "b", "a"])
        with pytest.raises(ValueError, match=r"vehicle_ids\[1\].*characters ','"):
            client.import_vehicles(["a", "b,c"])
        with pytest.raises(ValueError, match="129 characters"):
            client.import_vehicles(["x" * 129])
        with pytest.raises(TypeError, match="not one string"):
            client.import_vehicles("abc")
        assert client.import_vehicles([]) == VehicleImport()
    assert sent == []


def test_the_client_agrees_with_the_server_on_vehicle_ids() -> None:
    from edgepos_client import models

    assert models.VEHICLE_ID_PATTERN == schemas.VEHICLE_ID_PATTERN
    assert protocol.MAX_VEHICLES_PER_IMPORT == vehicle_schemas.MAX_VEHICLES_PER_IMPORT


def test_session_handle_keeps_superseded() -> None:
    assert Session("s", "s.t").superseded is None
