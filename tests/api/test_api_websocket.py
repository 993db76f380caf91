"""Batches over a WebSocket (/v1/sessions/{id}/ws): every frame answered exactly as the POST route answers
the same body (seq rules, replay, errors), the handshake refused as the POST route refuses the
credential, and the connection closed with its code when a frame is too large, the link idles or the
session ends."""

from __future__ import annotations

import json
from typing import Any

import pytest
from apihelp import ADMIN, assert_error, batch_body, bearer, make_settings, open_session, rsu_payload
from edgepos.api.app import create_app
from edgepos.store import MemoryStore
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse
from starlette.websockets import WebSocketDisconnect


def ws_path(session_id: str) -> str:
    return f"/v1/sessions/{session_id}/ws"


def exchange(websocket: Any, text: str) -> dict[str, Any]:
    websocket.send_text(text)
    return json.loads(websocket.receive_text())


def compact(body: dict[str, Any]) -> str:
    return json.dumps(body, separators=(",", ":"))


def frames_of_a_vehicle() -> list[str]:
    """Bodies a vehicle might send, good and bad, in order (raw text: some are not JSON)."""
    first = batch_body(1, 0, 2)
    return [
        compact(first),
        json.dumps(first, indent=2),  # the same batch again, other whitespace: replayed
        compact(batch_body(1, 2, 1)),  # seq 1 again with another body: 409
        compact(batch_body(3, 2, 1)),  # a gap: 409
        compact(batch_body(0, 2, 1)),  # seq out of bounds: 422
        '{\n  "seq": 2,\n  "measurements": [}\n}',  # not JSON: 422 naming line 3
        compact({"seq": 2, "measurements": [{"type": "rsu", "t": 0.1, "rsu_id": "S+000", "range": "far"}]}),
        compact({**batch_body(2, 2, 1), "colour": "red"}),  # an unknown field
        compact({"seq": 2, "measurements": [{"type": "pseudorange", "t": 0.2}]}),
        compact(batch_body(2, 2, 3)),
        compact(batch_body(2, 2, 3)),  # replayed
        "[]",
        '{"seq": 3, "measurements": [{"type": "gyro", "t": NaN, "yaw_rate": 0.0}]}',  # a non-finite literal
    ]


def test_every_frame_is_answered_as_the_post_route_answers_the_same_body(client):
    http_session, http_token = open_session(client, vehicle_id="car-http")
    ws_session, ws_token = open_session(client, vehicle_id="car-ws")
    seen = []
    with client.websocket_connect(ws_path(ws_session), headers=ws_token) as websocket:
        for number, text in enumerate(frames_of_a_vehicle(), start=1):
            posted = client.post(
                f"/v1/sessions/{http_session}/batches",
                content=text,
                headers={**http_token, "Content-Type": "application/json"},
            )
            answer = exchange(websocket, text)
            assert set(answer) == {"status", "seq", "frame", "request_id", "retry_after", "body"}
            assert answer["frame"] == number
            assert (answer["status"], answer["body"]) == (posted.status_code, posted.json()), text
            if posted.status_code == 200:
                assert answer["seq"] == posted.json()["seq"]
            seen.append(answer["status"])
    assert seen == [200, 200, 409, 409, 422, 422, 422, 422, 422, 200, 200, 422, 422]
    described = client.get(f"/v1/sessions/{ws_session}", headers=ADMIN).json()
    assert (described["last_seq"], described["batches"]) == (2, 2)


def test_answers_name_the_seq_and_the_frame_and_echo_the_request_id(client, caplog):
    session_id, token = open_session(client)
    headers = {**token, "X-Request-ID": "vehicle-link-7"}
    with client.websocket_connect(ws_path(session_id), headers=headers) as websocket:
        good = exchange(websocket, compact(batch_body(1, 0, 1)))
        gap = exchange(websocket, compact(batch_body(5, 1, 1)))
        broken = exchange(websocket, "{")
    assert (good["status"], good["seq"], good["frame"], good["request_id"]) == (200, 1, 1, "vehicle-link-7.1")
    assert good["body"]["seq"] == 1 and len(good["body"]["fixes"]) == 1
    assert (gap["status"], gap["seq"], gap["body"]["error"]["code"]) == (409, 5, "conflict")
    assert "the next seq is 2" in gap["body"]["error"]["message"]
    assert (broken["status"], broken["seq"], broken["frame"]) == (422, None, 3)
    assert broken["body"]["error"]["problems"][0]["reason"].startswith("not valid JSON at line 1, column 2")
    logged = [r for r in caplog.records if r.name == "edgepos.access" and getattr(r, "method", None) == "WS"]
    assert [r.status for r in logged] == [200, 409, 422]  # one access line per frame, as per POST
    metrics = client.get("/metrics").text
    assert (
        'edgepos_http_requests_total{method="WS",route="/v1/sessions/{session_id}/ws",status="409"} 1.0'
        in metrics
    )


def test_a_retry_on_a_new_connection_replays_the_stored_answer(client):
    session_id, token = open_session(client)
    text = compact(batch_body(1, 0, 3))
    with client.websocket_connect(ws_path(session_id), headers=token) as websocket:
        first = exchange(websocket, text)
    with client.websocket_connect(ws_path(session_id), headers=token) as websocket:
        again = exchange(websocket, text)
    posted = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 3), headers=token)
    assert first["body"] == again["body"] == posted.json()
    assert client.get(f"/v1/sessions/{session_id}", headers=token).json()["batches"] == 1


def test_the_admin_key_opens_any_sessions_socket(client):
    session_id, _token = open_session(client)
    with client.websocket_connect(ws_path(session_id), headers=ADMIN) as websocket:
        assert exchange(websocket, compact(batch_body(1, 0, 1)))["status"] == 200


@pytest.mark.parametrize("who", ["missing", "wrong secret", "another session", "not bearer"])
def test_a_refused_handshake_gets_the_http_error_of_the_post_route(client, who):
    session_id, token = open_session(client)
    _other_id, other_token = open_session(client, vehicle_id="car-2")
    headers = {
        "missing": {},
        "wrong secret": bearer(f"{session_id}.not-the-secret"),
        "another session": other_token,
        "not bearer": {"Authorization": token["Authorization"].replace("Bearer", "Basic")},
    }[who]
    posted = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 1), headers=headers)
    with (
        pytest.raises(WebSocketDenialResponse) as refused,
        client.websocket_connect(ws_path(session_id), headers=headers),
    ):
        pass
    status = 403 if who == "another session" else 401
    error = assert_error(refused.value, status, posted.json()["error"]["code"])
    assert refused.value.json() == posted.json()
    assert error["code"] == ("forbidden" if status == 403 else "unauthorized")
    if status == 401:
        assert refused.value.headers["www-authenticate"] == "Bearer"


def test_a_superseded_sessions_token_is_refused_with_409_at_the_handshake(client):
    old_id, old_token = open_session(client)
    new_id, _ = open_session(client)
    with (
        pytest.raises(WebSocketDenialResponse) as refused,
        client.websocket_connect(ws_path(old_id), headers=old_token),
    ):
        pass
    error = assert_error(refused.value, 409, "superseded")
    assert new_id in error["message"]


class WithoutDenialResponses:
    """An ASGI server without the WebSocket denial-response extension (the app must close instead)."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] == "websocket":
            scope = {**scope, "extensions": {}}
        await self.app(scope, receive, send)


def test_without_denial_responses_a_refused_handshake_closes_with_1008_and_a_json_reason(settings):
    with TestClient(WithoutDenialResponses(create_app(settings))) as client:
        session_id, _token = open_session(client)
        wrong = bearer(f"{session_id}.wrong")
        with (
            pytest.raises(WebSocketDisconnect) as closed,
            client.websocket_connect(ws_path(session_id), headers=wrong),
        ):
            pass
    assert closed.value.code == 1008
    assert json.loads(closed.value.reason) == {"status": 401, "code": "unauthorized"}


def test_a_session_superseded_while_connected_gets_an_error_frame_then_1008(client):
    session_id, token = open_session(client)
    with client.websocket_connect(ws_path(session_id), headers=token) as websocket:
        assert exchange(websocket, compact(batch_body(1, 0, 1)))["status"] == 200
        newer, _ = open_session(client)
        answer = exchange(websocket, compact(batch_body(2, 1, 1)))
        assert (answer["status"], answer["body"]["error"]["code"]) == (409, "superseded")
        assert newer in answer["body"]["error"]["message"]
        with pytest.raises(WebSocketDisconnect) as closed:
            websocket.receive_text()
    assert closed.value.code == 1008
    assert json.loads(closed.value.reason) == {"status": 409, "code": "superseded"}


@pytest.mark.parametrize(
    ("credential", "status", "code"), [("token", 401, "unauthorized"), ("admin", 404, "not_found")]
)
def test_a_session_deleted_while_connected_is_refused_as_over_http_then_1008(
    client, credential, status, code
):
    session_id, token = open_session(client)
    headers = token if credential == "token" else ADMIN
    with client.websocket_connect(ws_path(session_id), headers=headers) as websocket:
        assert exchange(websocket, compact(batch_body(1, 0, 1)))["status"] == 200
        assert client.delete(f"/v1/sessions/{session_id}", headers=ADMIN).status_code == 204
        posted = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(2, 1, 1), headers=headers)
        answer = exchange(websocket, compact(batch_body(2, 1, 1)))
        assert (answer["status"], answer["body"]) == (posted.status_code, posted.json())
        assert (answer["status"], answer["body"]["error"]["code"]) == (status, code)
        with pytest.raises(WebSocketDisconnect) as closed:
            websocket.receive_text()
    assert closed.value.code == 1008
    assert json.loads(closed.value.reason) == {"status": status, "code": code}


def test_a_frame_over_the_body_limit_closes_with_1009_and_changes_nothing(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, max_body_bytes=4096))) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        big = compact(batch_body(1, 0, 40))
        assert len(big.encode()) > 4096
        assert_error(
            client.post(f"/v1/sessions/{session_id}/batches", content=big, headers=token),
            413,
            "payload_too_large",
        )
        with client.websocket_connect(ws_path(session_id), headers=token) as websocket:
            assert exchange(websocket, compact(batch_body(1, 0, 1)))["status"] == 200
            websocket.send_text(compact(batch_body(2, 1, 40)))
            with pytest.raises(WebSocketDisconnect) as closed:
                websocket.receive_text()
        assert closed.value.code == 1009
        assert json.loads(closed.value.reason) == {"status": 413, "code": "payload_too_large"}
        assert client.get(f"/v1/sessions/{session_id}", headers=ADMIN).json()["last_seq"] == 1


def test_a_binary_frame_is_415_and_the_link_stays_open(client):
    session_id, token = open_session(client)
    with client.websocket_connect(ws_path(session_id), headers=token) as websocket:
        websocket.send_bytes(compact(batch_body(1, 0, 1)).encode())
        answer = json.loads(websocket.receive_text())
        assert (answer["status"], answer["seq"], answer["body"]["error"]["code"]) == (
            415,
            None,
            "unsupported_media_type",
        )
        assert exchange(websocket, compact(batch_body(1, 0, 1)))["status"] == 200


def test_an_idle_link_is_closed_with_1000(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, ws_idle_timeout_s=0.2))) as client:
        session_id, token = open_session(client)
        with (
            client.websocket_connect(ws_path(session_id), headers=token) as websocket,
            pytest.raises(WebSocketDisconnect) as closed,
        ):
            websocket.receive_text()
    assert closed.value.code == 1000
    assert json.loads(closed.value.reason) == {"status": 408, "code": "idle_timeout"}


class FrozenClock:
    def __call__(self) -> float:
        return 1_000_000.0


def test_every_frame_counts_against_the_sessions_request_rate(tmp_path):
    settings = make_settings(tmp_path, rate_limit_per_s=0.5, rate_limit_burst=3)
    store = MemoryStore(settings.session_ttl_s, FrozenClock())
    with TestClient(create_app(settings, store=store)) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        with client.websocket_connect(ws_path(session_id), headers=token) as websocket:  # the handshake: 1
            answers = [exchange(websocket, compact(batch_body(seq, seq - 1, 1))) for seq in (1, 2, 3)]
        assert [answer["status"] for answer in answers] == [200, 200, 429]
        limited = answers[2]
        assert limited["body"]["error"]["code"] == "rate_limited"
        assert limited["seq"] == 3 and 1 <= limited["retry_after"] <= 2
        assert client.get(f"/v1/sessions/{session_id}", headers=ADMIN).json()["last_seq"] == 2


def test_links_beyond_the_workers_maximum_are_refused_503_with_retry_after(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, ws_max_connections=2))) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        sessions = [open_session(client, vehicle_id=f"car-{n}") for n in range(3)]
        (first, first_token), (second, second_token), (third, third_token) = sessions
        with client.websocket_connect(ws_path(first), headers=first_token) as one:
            with (
                client.websocket_connect(ws_path(second), headers=second_token),
                pytest.raises(WebSocketDenialResponse) as refused,
                client.websocket_connect(ws_path(third), headers=third_token),
            ):
                pass
            error = assert_error(refused.value, 503, "unavailable")
            assert "EDGEPOS_WS_MAX_CONNECTIONS" in error["message"]
            assert refused.value.headers["retry-after"] == "5"
            assert exchange(one, compact(batch_body(1, 0, 1)))["status"] == 200
        with client.websocket_connect(ws_path(third), headers=third_token) as three:  # room again
            assert exchange(three, compact(batch_body(1, 0, 1)))["status"] == 200


def test_a_bug_while_applying_is_a_500_frame_and_the_link_stays_open(client, monkeypatch):
    from edgepos.api import session_service

    session_id, token = open_session(client)
    real = session_service.apply_batch
    calls = []

    async def broken_once(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("a bug")
        return await real(*args, **kwargs)

    monkeypatch.setattr(session_service, "apply_batch", broken_once)
    with client.websocket_connect(ws_path(session_id), headers=token) as websocket:
        failed = exchange(websocket, compact(batch_body(1, 0, 1)))
        assert (failed["status"], failed["body"]["error"]["code"]) == (500, "internal_error")
        assert "a bug" not in failed["body"]["error"]["message"]
        assert exchange(websocket, compact(batch_body(1, 0, 1)))["status"] == 200


def test_a_valid_frame_is_validated_in_one_pass_without_decoding_it_first(client, monkeypatch):
    from edgepos.api import batch_socket

    client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
    session_id, token = open_session(client)

    def refuse(text: str) -> Any:
        raise AssertionError(f"a valid frame was decoded first: {text[:40]}")

    monkeypatch.setattr(batch_socket, "decode_frame", refuse)
    with client.websocket_connect(ws_path(session_id), headers=token) as websocket:
        answer = exchange(websocket, compact(batch_body(1, 0, 3)))
    assert answer["status"] == 200, answer
