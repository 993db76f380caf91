"""The async client against the real app in-process (httpx.ASGITransport): every call, errors
carrying the server's code and message, and a batch retried after a lost reply applied once."""

from __future__ import annotations

import httpx
import pytest
from clienthelp import ADMIN_KEY, INITIAL_STATE, batch, make_app, scenario_rsus
from edgepos_client import (
    AsyncEdgeposClient,
    Conflict,
    Forbidden,
    GyroMeasurement,
    InvalidRequest,
    NotFound,
    PayloadTooLarge,
    Rsu,
    Session,
    TooManySessions,
    TransportError,
    Unauthorized,
)

pytestmark = pytest.mark.anyio


async def test_rsu_registry_round_trip(aclient: AsyncEdgeposClient) -> None:
    rsus = await aclient.list_rsus()
    assert {rsu.id for rsu in rsus} == {rsu.id for rsu in scenario_rsus()}
    stored = await aclient.put_rsu(Rsu(id="X-1", x=1.5, y=-2.0, range_std=0.5, radius=100.0))
    assert stored == Rsu(id="X-1", x=1.5, y=-2.0, range_std=0.5, bearing_std=None, radius=100.0)
    assert await aclient.get_rsu("X-1") == stored
    await aclient.delete_rsu("X-1")
    with pytest.raises(NotFound) as caught:
        await aclient.get_rsu("X-1")
    assert caught.value.status == 404 and caught.value.code == "not_found" and "X-1" in caught.value.message


async def test_pipelines_list_options(aclient: AsyncEdgeposClient) -> None:
    pipelines = {pipeline.name: pipeline for pipeline in await aclient.pipelines()}
    assert {"rsu_imu", "gnss_tight", "v2x_federated"} <= set(pipelines)
    assert set(pipelines["rsu_imu"].measurement_types) == {"rsu", "gyro"}
    assert "filter" in {option.name for option in pipelines["rsu_imu"].options}
    assert pipelines["gnss_tight"].measurement_types == ["pseudorange", "riss"]
    particles = {option.name: option for option in pipelines["gnss_tight"].options}["particles"]
    assert (particles.default, particles.minimum, particles.maximum) == (200, 10, 700)


async def test_session_lifecycle_tracks_seq(aclient: AsyncEdgeposClient) -> None:
    session = await aclient.create_session("car-1", initial_state=INITIAL_STATE)
    assert session.vehicle_id == "car-1" and session.pipeline == "rsu_imu" and session.last_seq == 0
    assert session.options["filter"] == "ckf"
    first = await aclient.send_batch(session, batch(0, 5))
    second = await aclient.send_batch(session, batch(5, 3), include_state=True)
    assert [len(first), len(second)] == [5, 3]
    assert session.last_seq == 2
    assert [fix.t for fix in first + second] == pytest.approx([0.05 * k for k in range(1, 9)])
    assert first[0].state is None and second[0].state is not None
    assert second[-1].position_covariance is not None and len(second[-1].position_covariance) == 2
    info = await aclient.get_session(session)
    assert (info.last_seq, info.batches, info.epochs, info.initialised) == (2, 2, 8, True)
    assert info.last_fix is not None and info.last_fix.t == second[-1].t
    admin_view = await aclient.get_session(session.session_id)  # a bare id opens with the admin key
    assert admin_view.session_id == session.session_id
    await aclient.delete_session(session)
    with pytest.raises(NotFound):
        await aclient.get_session(session.session_id)  # the admin key learns it is gone
    with pytest.raises(Unauthorized):
        await aclient.get_session(session)  # its token opens nothing any more


async def test_refused_batch_raises_with_every_problem(aclient: AsyncEdgeposClient) -> None:
    session = await aclient.create_session("car-2", initial_state=INITIAL_STATE)
    bad = [*batch(0, 1), {"type": "rsu", "t": 0.05, "rsu_id": "nowhere", "range": 5.0, "bearing": 0.1}]
    with pytest.raises(InvalidRequest) as caught:
        await aclient.send_batch(session, bad)
    error = caught.value
    assert error.status == 422 and error.code == "invalid_request"
    assert "unchanged" in error.message
    assert [(p.index, p.field) for p in error.problems] == [
        (len(bad) - 1, f"measurements[{len(bad) - 1}].rsu_id")
    ]
    assert "nowhere" in error.problems[0].reason and "nowhere" in str(error)
    assert session.last_seq == 0  # a refused batch does not advance the handle
    assert len(await aclient.send_batch(session, batch(0, 1))) == 1
    assert session.last_seq == 1


async def test_seq_conflicts_are_409(aclient: AsyncEdgeposClient) -> None:
    session = await aclient.create_session("car-3", initial_state=INITIAL_STATE)
    await aclient.send_batch(session, batch(0, 2))
    with pytest.raises(Conflict) as caught:
        await aclient.send_batch(session, batch(2, 2), seq=5)
    assert caught.value.status == 409 and "next seq is 2" in caught.value.message
    with pytest.raises(Conflict):
        await aclient.send_batch(session, batch(2, 2), seq=1)  # last seq, different body


async def test_credentials_errors(tmp_path) -> None:
    transport = httpx.ASGITransport(app=make_app(tmp_path))
    async with AsyncEdgeposClient("http://edgepos.test", "wrong-key", transport=transport) as stranger:
        with pytest.raises(Unauthorized) as caught:
            await stranger.put_rsus(scenario_rsus())
        assert caught.value.status == 401 and "bearer credential is not valid" in caught.value.message
        with pytest.raises(Unauthorized):
            await stranger.create_session("car-4")  # opening a session needs a credential too
    async with AsyncEdgeposClient("http://edgepos.test", ADMIN_KEY, transport=transport) as admin:
        session = await admin.create_session("car-4")
    async with AsyncEdgeposClient("http://edgepos.test", session.token, transport=transport) as vehicle:
        with pytest.raises(Forbidden) as forbidden:
            await vehicle.put_rsus(scenario_rsus())
        assert forbidden.value.status == 403 and forbidden.value.code == "forbidden"
        assert await vehicle.list_rsus() == []  # any session token may read the registry
    async with AsyncEdgeposClient("http://edgepos.test", ADMIN_KEY, transport=transport) as admin:
        await admin.put_rsus(scenario_rsus())
        assert len(await admin.list_rsus(session)) == len(scenario_rsus())  # read with the session's token


async def test_limits_map_to_their_exceptions(tmp_path) -> None:
    transport = httpx.ASGITransport(app=make_app(tmp_path, max_sessions=1, max_body_bytes=2048))
    async with AsyncEdgeposClient("http://edgepos.test", ADMIN_KEY, transport=transport) as client:
        await client.put_rsus(scenario_rsus()[:4])
        session = await client.create_session("only-one")
        with pytest.raises(TooManySessions) as too_many:
            await client.create_session("second")
        assert too_many.value.status == 429 and too_many.value.code == "too_many_sessions"
        big = [GyroMeasurement(t=0.05 * k, yaw_rate=0.0) for k in range(1, 200)]
        with pytest.raises(PayloadTooLarge) as too_large:
            await client.send_batch(session, big)
        assert too_large.value.status == 413


class LoseFirstReply(httpx.AsyncBaseTransport):
    """Forwards every request to the app, but for the first batch POST drops the answer and raises
    a read timeout, as when the reply is lost on the way back."""

    def __init__(self, inner: httpx.AsyncBaseTransport) -> None:
        self.inner = inner
        self.batch_bodies: list[bytes] = []
        self.lost = False

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        response = await self.inner.handle_async_request(request)
        if request.method == "POST" and request.url.path.endswith("/batches"):
            self.batch_bodies.append(request.content)
            if not self.lost:
                self.lost = True
                await response.aread()
                raise httpx.ReadTimeout("reply lost", request=request)
        return response


async def test_batch_retried_after_lost_reply_is_applied_once(tmp_path) -> None:
    transport = LoseFirstReply(httpx.ASGITransport(app=make_app(tmp_path)))
    async with AsyncEdgeposClient(
        "http://edgepos.test", ADMIN_KEY, transport=transport, backoff=0.0
    ) as client:
        await client.put_rsus(scenario_rsus())
        session = await client.create_session("retry-car", initial_state=INITIAL_STATE)
        fixes = await client.send_batch(session, batch(0, 4))
        info = await client.get_session(session)
    assert len(transport.batch_bodies) == 2
    assert transport.batch_bodies[0] == transport.batch_bodies[1]  # same seq, same bytes
    assert b'"seq":1,' in transport.batch_bodies[0]
    assert (info.last_seq, info.batches, info.epochs) == (1, 1, 4)  # applied once
    assert info.last_fix == fixes[-1]
    assert session.last_seq == 1


class CountingTransport(httpx.AsyncBaseTransport):
    def __init__(
        self, inner: httpx.AsyncBaseTransport, fail_with: type[httpx.TransportError] | None = None
    ) -> None:
        self.inner = inner
        self.fail_with = fail_with
        self.requests: list[httpx.Request] = []

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        if self.fail_with is not None and request.url.path == "/v1/sessions":
            raise self.fail_with("simulated", request=request)
        return await self.inner.handle_async_request(request)


async def test_a_4xx_is_never_retried(tmp_path) -> None:
    transport = CountingTransport(httpx.ASGITransport(app=make_app(tmp_path)))
    async with AsyncEdgeposClient(
        "http://edgepos.test", ADMIN_KEY, transport=transport, retries=5, backoff=0.0
    ) as client:
        session = await client.create_session("no-rsus", initial_state=INITIAL_STATE)
        with pytest.raises(InvalidRequest):
            await client.send_batch(session, batch(0, 1))  # no RSU is registered on this app
    assert [r.method for r in transport.requests] == ["POST", "POST"]


@pytest.mark.parametrize(
    ("failure", "attempts"),
    [(httpx.ConnectError, 3), (httpx.ReadTimeout, 1)],
    ids=["connect-error-retried", "read-timeout-not-retried"],
)
async def test_session_creation_retries_only_unsent_requests(tmp_path, failure, attempts) -> None:
    """Opening a session is not idempotent: only a request that never reached the server is retried."""
    transport = CountingTransport(httpx.ASGITransport(app=make_app(tmp_path)), fail_with=failure)
    async with AsyncEdgeposClient(
        "http://edgepos.test", ADMIN_KEY, transport=transport, retries=2, backoff=0.0
    ) as client:
        with pytest.raises(TransportError) as caught:
            await client.create_session("unlucky")
    assert len(transport.requests) == attempts
    assert caught.value.status is None and f"after {attempts} attempt" in caught.value.message


async def test_session_handle_can_be_rebuilt(aclient: AsyncEdgeposClient) -> None:
    """A vehicle that restarts resumes its session from the stored id, token and last seq."""
    session = await aclient.create_session("resume-car", initial_state=INITIAL_STATE)
    await aclient.send_batch(session, batch(0, 2))
    resumed = Session(session.session_id, session.token, last_seq=session.last_seq)
    fixes = await aclient.send_batch(resumed, batch(2, 2))
    assert resumed.last_seq == 2 and len(fixes) == 2
