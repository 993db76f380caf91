"""The blocking client over httpx.MockTransport: error bodies become exceptions, Retry-After,
non-JSON failures, and the bounded retry of a batch with the same bytes."""

from __future__ import annotations

import json
from collections.abc import Callable

import httpx
import pytest
from edgepos_client import (
    EdgeposClient,
    GyroMeasurement,
    InvalidRequest,
    RateLimited,
    RsuMeasurement,
    ServerError,
    Session,
    TransportError,
    Unavailable,
)

Handler = Callable[[httpx.Request], httpx.Response]


def error(
    status: int, code: str, message: str, problems: list[dict] | None = None, **headers: str
) -> httpx.Response:
    body = {"error": {"code": code, "message": message, "problems": problems or []}}
    return httpx.Response(status, json=body, headers=headers)


def batch_answer(request: httpx.Request) -> httpx.Response:
    body = json.loads(request.content)
    times = sorted({m["t"] for m in body["measurements"]})
    fixes = [
        {
            "t": t,
            "status": "predicted",
            "x": 1.0,
            "y": 2.0,
            "vx": 0.0,
            "vy": 0.0,
            "speed": 0.0,
            "heading": 0.0,
            "yaw_rate": 0.0,
            "latitude": None,
            "longitude": None,
            "position_covariance": [[1.0, 0.0], [0.0, 1.0]],
            "state": None,
            "model_probabilities": {"ca": 1.0},
            "nis": None,
            "nis_dof": 0,
            "measurements": [],
            "a_field_from_a_newer_server": 1,
        }
        for t in times
    ]
    return httpx.Response(200, json={"seq": body["seq"], "fixes": fixes})


def client_with(handler: Handler, **options: object) -> EdgeposClient:
    return EdgeposClient(
        "http://edgepos.test", "admin", transport=httpx.MockTransport(handler), backoff=0.0, **options
    )


SESSION = Session("abc", "abc.secret")
MEASUREMENTS = [
    RsuMeasurement(t=0.1, rsu_id="S+000", range=4.0, bearing=0.5),
    GyroMeasurement(t=0.1, yaw_rate=0.01),
]


def test_error_body_becomes_exception_with_server_fields() -> None:
    problems = [{"index": 1, "field": "measurements[1].range", "reason": "must be >= 0"}]

    def handler(request: httpx.Request) -> httpx.Response:
        return error(
            422, "invalid_request", "the request is invalid (1 problem)", problems, **{"X-Request-ID": "r-1"}
        )

    with client_with(handler) as client, pytest.raises(InvalidRequest) as caught:
        client.send_batch(Session("abc", "abc.secret"), MEASUREMENTS)
    raised = caught.value
    assert (raised.status, raised.code, raised.request_id) == (422, "invalid_request", "r-1")
    assert raised.message == "the request is invalid (1 problem)"
    assert [(p.index, p.field, p.reason) for p in raised.problems] == [
        (1, "measurements[1].range", "must be >= 0")
    ]
    assert "measurements[1].range (#1): must be >= 0" in str(raised)


def test_rate_limited_carries_retry_after() -> None:
    with (
        client_with(lambda r: error(429, "rate_limited", "slow down", **{"Retry-After": "3"})) as client,
        pytest.raises(RateLimited) as caught,
    ):
        client.pipelines()
    assert caught.value.retry_after == 3.0 and caught.value.status == 429


def test_non_json_failure_still_maps_by_status() -> None:
    with (
        client_with(lambda r: httpx.Response(502, text="bad gateway")) as client,
        pytest.raises(ServerError) as caught,
    ):
        client.list_rsus()
    assert caught.value.status == 502 and caught.value.message == "bad gateway"


def test_bearer_and_body_of_a_batch() -> None:
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return batch_answer(request)

    session = Session("abc", "abc.secret", last_seq=4)
    with client_with(handler) as client:
        fixes = client.send_batch(session, MEASUREMENTS)
        client.send_batch(session, [{"type": "gyro", "t": 0.15, "yaw_rate": 0.1 + 0.2}])
    assert len(fixes) == 1 and fixes[0].t == 0.1 and session.last_seq == 6
    first = seen[0]
    assert first.url.path == "/v1/sessions/abc/batches"
    assert first.headers["authorization"] == "Bearer abc.secret"
    assert json.loads(first.content) == {
        "seq": 5,
        "measurements": [
            {"type": "rsu", "t": 0.1, "rsu_id": "S+000", "range": 4.0, "bearing": 0.5},
            {"type": "gyro", "t": 0.1, "yaw_rate": 0.01},
        ],
        "include_state": False,
    }
    assert (
        json.loads(seen[1].content)["measurements"][0]["yaw_rate"] == 0.1 + 0.2
    )  # floats round-trip exactly


def test_measurement_dicts_are_checked_before_sending() -> None:
    with client_with(batch_answer) as client:
        with pytest.raises(ValueError):
            client.send_batch(
                SESSION, [{"type": "rsu", "t": 0.1, "rsu_id": "S+000", "range": -1.0, "bearing": 0.0}]
            )
        with pytest.raises(ValueError):
            client.send_batch(SESSION, [{"type": "gyro", "t": float("nan"), "yaw_rate": 0.0}])
        with pytest.raises(TypeError, match="seq explicitly"):
            client.send_batch("abc", MEASUREMENTS)  # a bare session id has no seq to track


def test_batch_retried_after_503_and_timeouts_with_identical_bytes() -> None:
    bodies: list[bytes] = []

    def handler(request: httpx.Request) -> httpx.Response:
        bodies.append(request.content)
        if len(bodies) == 1:
            raise httpx.ReadTimeout("lost", request=request)
        if len(bodies) == 2:
            return error(503, "unavailable", "retry the same batch")
        return batch_answer(request)

    session = Session("abc", "abc.secret")
    with client_with(handler, retries=3) as client:
        fixes = client.send_batch(session, MEASUREMENTS)
    assert len(bodies) == 3 and len(set(bodies)) == 1
    assert len(fixes) == 1 and session.last_seq == 1


def test_retries_are_bounded() -> None:
    attempts: list[int] = []

    def always_times_out(request: httpx.Request) -> httpx.Response:
        attempts.append(1)
        raise httpx.ConnectTimeout("no route", request=request)

    session = Session("abc", "abc.secret")
    with client_with(always_times_out, retries=2) as client, pytest.raises(TransportError) as caught:
        client.send_batch(session, MEASUREMENTS)
    assert len(attempts) == 3 and caught.value.code == "timeout" and session.last_seq == 0

    with (
        client_with(lambda r: error(503, "unavailable", "busy"), retries=1) as client,
        pytest.raises(Unavailable),
    ):
        client.send_batch(session, MEASUREMENTS)


def test_unknown_error_code_falls_back_on_status() -> None:
    with (
        client_with(lambda r: error(422, "some_future_code", "new kind of refusal")) as client,
        pytest.raises(InvalidRequest) as caught,
    ):
        client.pipelines()
    assert caught.value.code == "some_future_code"
