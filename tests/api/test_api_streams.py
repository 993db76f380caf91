"""GET /v1/stream/fixes on the in-process and SQLite stores: every applied fix as a server-sent event,
filters, the 401/403/422 refusals, resume with Last-Event-ID from the bounded buffer (and the missed event
when it no longer holds the gap), max_rate_hz decimation, and a consumer that never reads: batches keep
completing and it is dropped with a final event."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from apihelp import ADMIN, assert_error, batch_body, make_settings, open_session, rsu_payload
from edgepos.api.app import create_app
from edgepos.api.schemas import FixEventOut, StreamEndOut, StreamMissedOut
from fastapi.testclient import TestClient
from ssehelp import Event, events, take, until_ping

STREAM = "/v1/stream/fixes"


def _client(tmp_path: Path, **overrides: Any) -> TestClient:
    settings = make_settings(tmp_path, stream_ping_s=0.3, rate_limit_per_s=0, **overrides)
    return TestClient(create_app(settings))


@pytest.fixture(params=["memory", "sqlite"])
def client(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[TestClient]:
    store = "memory" if request.param == "memory" else f"sqlite:///{tmp_path}/edgepos.db"
    with _client(tmp_path, store=store) as test_client:
        assert test_client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
        yield test_client


def _post(
    client: TestClient, session_id: str, auth: dict[str, str], seq: int, first: int, count: int
) -> list[dict[str, Any]]:
    response = client.post(
        f"/v1/sessions/{session_id}/batches", json=batch_body(seq, first, count), headers=auth
    )
    assert response.status_code == 200, response.text
    return list(response.json()["fixes"])


def _fixes(found: list[Event]) -> list[Event]:
    return [event for event in found if event.event == "fix"]


def test_admin_stream_carries_every_fix_of_a_batch_as_the_batch_answer_serialises_it(client: TestClient):
    session_id, auth = open_session(client)
    with client.stream("GET", STREAM, headers=ADMIN) as response:
        assert response.status_code == 200
        assert response.headers["content-type"].startswith("text/event-stream")
        assert response.headers["cache-control"] == "no-cache"
        stream = events(response.iter_lines())
        answered = _post(client, session_id, auth, 1, 0, 5)
        got = _fixes(take(stream, 5))
        assert until_ping(stream) == []  # nothing more
    assert len(got) == 5
    ids = [int(event.id or 0) for event in got]
    assert ids == list(range(ids[0], ids[0] + 5))
    for event, fix in zip(got, answered):
        data = event.json()
        FixEventOut.model_validate(data)
        assert data == {
            "session_id": session_id,
            "vehicle_id": "car-1",
            "pipeline": "rsu_imu",
            "seq": 1,
            "fix": {**fix, "state": None},
        }


def test_filters_by_vehicle_and_pipeline(client: TestClient):
    one, auth_one = open_session(client, vehicle_id="car-1")
    two, auth_two = open_session(client, vehicle_id="car-2")
    with (
        client.stream("GET", STREAM, params={"vehicle_id": "car-2"}, headers=ADMIN) as only_two,
        client.stream(
            "GET", STREAM, params=[("vehicle_id", "car-1,car-2"), ("pipeline", "rsu_imu")], headers=ADMIN
        ) as both,
        client.stream("GET", STREAM, params={"pipeline": "gnss_tight"}, headers=ADMIN) as none,
        client.stream("GET", STREAM, params={"session_id": one}, headers=ADMIN) as session_one,
    ):
        _post(client, one, auth_one, 1, 0, 3)
        _post(client, two, auth_two, 1, 0, 2)
        two_events = events(only_two.iter_lines())
        got_two = _fixes(take(two_events, 2) + until_ping(two_events))
        got_both = _fixes(take(events(both.iter_lines()), 5))
        got_none = until_ping(events(none.iter_lines()))
        got_one = _fixes(take(events(session_one.iter_lines()), 3))
    assert [e.json()["vehicle_id"] for e in got_two] == ["car-2", "car-2"]
    assert sorted(e.json()["vehicle_id"] for e in got_both) == ["car-1"] * 3 + ["car-2"] * 2
    assert got_none == []
    assert {e.json()["session_id"] for e in got_one} == {one} and len(got_one) == 3


def test_a_session_token_streams_its_own_session_only(client: TestClient):
    mine, auth_mine = open_session(client, vehicle_id="car-1")
    other, auth_other = open_session(client, vehicle_id="car-2")
    assert_error(client.get(STREAM, params={"session_id": other}, headers=auth_mine), 403, "forbidden")
    with client.stream("GET", STREAM, headers=auth_mine) as response:
        assert response.status_code == 200
        stream = events(response.iter_lines())
        _post(client, other, auth_other, 1, 0, 3)
        _post(client, mine, auth_mine, 1, 0, 2)
        got = _fixes(take(stream, 2)) + _fixes(until_ping(stream))
    assert [e.json()["session_id"] for e in got] == [mine, mine]
    with client.stream("GET", STREAM, params={"session_id": mine}, headers=auth_mine) as response:
        assert response.status_code == 200


def test_a_token_stream_ends_when_its_session_ends(client: TestClient):
    session_id, auth = open_session(client)
    with client.stream("GET", STREAM, headers=auth) as response:
        stream = events(response.iter_lines())
        assert client.delete(f"/v1/sessions/{session_id}", headers=ADMIN).status_code == 204
        found = take(stream, 0, until="end")
    end = found[-1]
    assert end.event == "end"
    assert StreamEndOut.model_validate(end.json()).reason == "session_ended"


def test_refusals(client: TestClient):
    assert_error(client.get(STREAM), 401, "unauthorized")
    registered = client.post("/v1/vehicles", json={"vehicle_id": "car-9"}, headers=ADMIN)
    assert registered.status_code == 201, registered.text
    vehicle = {"Authorization": f"Bearer {registered.json()['key']}"}
    assert_error(client.get(STREAM, headers=vehicle), 403, "forbidden")  # a vehicle key opens sessions only
    cases = [
        ({"pipeline": "nope"}, "pipeline"),
        ({"pipeline": "rsu_imu,nope"}, "pipeline"),
        ({"vehicle_id": "car 1,bad!id"}, "vehicle_id"),
        ({"max_rate_hz": "0"}, "max_rate_hz"),
        ({"max_rate_hz": "1000"}, "max_rate_hz"),
        ({"max_rate_hz": "nan"}, "max_rate_hz"),
        ({"last_event_id": "abc"}, "last_event_id"),
        ({"pipline": "rsu_imu"}, "pipline"),
    ]
    for params, field in cases:
        error = assert_error(client.get(STREAM, params=params, headers=ADMIN), 422, "invalid_request")
        assert any(field in str(problem["field"]) for problem in error["problems"]), (params, error)
    error = assert_error(
        client.get(STREAM, headers={**ADMIN, "Last-Event-ID": "12-x"}), 422, "invalid_request"
    )
    assert error["problems"][0]["field"] == "Last-Event-ID"
    assert (
        "nope"
        in assert_error(
            client.get(STREAM, params={"pipeline": "nope"}, headers=ADMIN), 422, "invalid_request"
        )["message"]
    )


def test_resume_with_last_event_id_gives_exactly_the_missed_fixes(client: TestClient):
    session_id, auth = open_session(client)
    with client.stream("GET", STREAM, headers=ADMIN) as response:
        stream = events(response.iter_lines())
        _post(client, session_id, auth, 1, 0, 3)
        seen = _fixes(take(stream, 3))
    last = seen[-1].id
    assert last is not None
    _post(client, session_id, auth, 2, 3, 4)  # while nobody listens
    with client.stream("GET", STREAM, headers={**ADMIN, "Last-Event-ID": last}) as response:
        stream = events(response.iter_lines())
        missed = _fixes(take(stream, 4))
        assert until_ping(stream) == []
        _post(client, session_id, auth, 3, 7, 1)
        live = _fixes(take(stream, 1))
    assert [int(e.id or 0) for e in missed] == [int(last) + n for n in (1, 2, 3, 4)]
    assert [e.json()["seq"] for e in missed] == [2, 2, 2, 2]
    assert int(live[0].id or 0) == int(last) + 5 and live[0].json()["seq"] == 3
    # the query parameter does the same (for clients that cannot set headers)
    with client.stream(
        "GET", STREAM, params={"last_event_id": str(int(last) + 3)}, headers=ADMIN
    ) as response:
        again = _fixes(take(events(response.iter_lines()), 2))
    assert [int(e.id or 0) for e in again] == [int(last) + 4, int(last) + 5]


def test_an_id_older_than_the_buffer_gets_a_missed_event_first(tmp_path: Path):
    with _client(tmp_path, stream_buffer=10) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, auth = open_session(client)
        with client.stream("GET", STREAM, headers=ADMIN) as response:
            stream = events(response.iter_lines())
            _post(client, session_id, auth, 1, 0, 1)
            first = _fixes(take(stream, 1))[0]
        for seq in range(2, 6):
            _post(client, session_id, auth, seq, 1 + 5 * (seq - 2), 5)  # 20 more fixes: the buffer keeps 10
        start = int(first.id or 0)
        with client.stream("GET", STREAM, headers={**ADMIN, "Last-Event-ID": str(start)}) as response:
            found = take(events(response.iter_lines()), 10)
        with client.stream("GET", STREAM, headers={**ADMIN, "Last-Event-ID": str(start + 1000)}) as response:
            ahead = take(events(response.iter_lines()), 10)
    missed = StreamMissedOut.model_validate(found[0].json())
    assert found[0].event == "missed" and found[0].id is None
    assert missed.reason == "trimmed" and missed.missed == 10 and missed.oldest_event_id == str(start + 11)
    assert [int(e.id or 0) for e in found[1:]] == list(range(start + 11, start + 21))
    assert (
        ahead[0].event == "missed"
        and ahead[0].json()["reason"] == "unknown"
        and ahead[0].json()["missed"] is None
    )
    assert [int(e.id or 0) for e in ahead[1:]] == list(range(start + 11, start + 21))


def test_max_rate_hz_decimates_per_vehicle(client: TestClient):
    one, auth_one = open_session(client, vehicle_id="car-1")
    two, auth_two = open_session(client, vehicle_id="car-2")
    with client.stream("GET", STREAM, params={"max_rate_hz": "5"}, headers=ADMIN) as response:
        stream = events(response.iter_lines())
        answered = _post(client, one, auth_one, 1, 0, 20) + _post(client, two, auth_two, 1, 0, 20)
        got = _fixes(take(stream, 1)) + _fixes(until_ping(stream))
    # what the rule keeps: per vehicle, a fix at least 0.2 s after the last one sent
    expected: list[float] = []
    last: float | None = None
    for fix in answered[:20]:
        if last is None or abs(fix["t"] - last) >= 0.2 - 1e-6:
            expected.append(fix["t"])
            last = fix["t"]
    assert 3 <= len(expected) < 20
    for vehicle in ("car-1", "car-2"):
        times = [e.json()["fix"]["t"] for e in got if e.json()["vehicle_id"] == vehicle]
        assert times == expected


def test_a_consumer_that_never_reads_does_not_stall_batches_and_is_dropped(tmp_path: Path):
    with _client(tmp_path, stream_queue=30) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, auth = open_session(client)
        with (
            client.stream("GET", STREAM, headers=ADMIN) as stuck,
            client.stream("GET", STREAM, params={"max_rate_hz": "100"}, headers=ADMIN) as reader,
        ):
            reading = events(reader.iter_lines())
            total = 0
            for seq in range(1, 7):  # 120 fixes while `stuck` reads nothing: its queue holds 30
                total += len(_post(client, session_id, auth, seq, 20 * (seq - 1), 20))
                assert len(_fixes(take(reading, 20))) == 20  # the other consumer keeps up
            found = take(events(stuck.iter_lines()), 0, until="end")
        metrics = client.get("/metrics").text
    assert total == 120
    end = found[-1]
    assert end.event == "end" and StreamEndOut.model_validate(end.json()).reason == "slow_consumer"
    assert len(_fixes(found)) <= 30
    assert end.json()["last_event_id"] == (_fixes(found)[-1].id if _fixes(found) else None)
    dropped = [
        line
        for line in metrics.splitlines()
        if line.startswith('edgepos_stream_events_dropped_total{reason="slow_consumer"}')
    ]
    assert dropped and float(dropped[0].split()[-1]) >= 1


def test_metrics_count_consumers_and_events(client: TestClient):
    session_id, auth = open_session(client)
    with client.stream("GET", STREAM, headers=ADMIN) as response:
        stream = events(response.iter_lines())
        _post(client, session_id, auth, 1, 0, 3)
        take(stream, 3)
        during = client.get("/metrics").text
    assert "edgepos_stream_consumers 1.0" in during
    assert "edgepos_stream_events_sent_total 3.0" in during


def test_the_schema_documents_the_stream(client: TestClient):
    document = client.get("/openapi.json").json()
    route = document["paths"][STREAM]["get"]
    assert set(route["responses"]) == {"200", "401", "403", "422", "429", "503"}
    assert route["responses"]["200"]["content"]["text/event-stream"]["schema"]["$ref"].endswith(
        "/FixEventOut"
    )
    for name in ("FixEventOut", "StreamMissedOut", "StreamEndOut"):
        assert name in document["components"]["schemas"]
    names = {parameter["name"] for parameter in route["parameters"]}
    assert names == {"session_id", "pipeline", "vehicle_id", "max_rate_hz", "last_event_id", "Last-Event-ID"}
