"""The batch WebSocket against a real server process over a real loopback socket: the client's
``websocket(session)`` (sync and async) returns what ``send_batch`` over HTTP returns and raises the same
errors; the server (uvicorn with its websockets implementation, as ``edgepos serve`` runs it) refuses a
handshake with the HTTP error and closes with 1009 on a frame over the body limit."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from clienthelp import ADMIN_KEY, INITIAL_STATE, batch, scenario_rsus
from edgepos.loadgen.localserver import clean_environment, running, serve_command
from edgepos_client import (
    AsyncEdgeposClient,
    Conflict,
    EdgeposClient,
    InvalidRequest,
    Session,
    Superseded,
    Unauthorized,
)
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.protocol import State
from websockets.sync.client import connect

pytestmark = pytest.mark.slow


def ws_url(server_url: str, session_id: str) -> str:
    return server_url.replace("http://", "ws://") + f"/v1/sessions/{session_id}/ws"


def test_batches_over_the_socket_match_http_batches(server_url: str) -> None:
    with EdgeposClient(server_url, ADMIN_KEY, timeout=10.0) as client:
        client.put_rsus(scenario_rsus())
        over_http = client.create_session("ws-twin-http", initial_state=INITIAL_STATE)
        over_ws = client.create_session("ws-twin-ws", initial_state=INITIAL_STATE)
        with client.websocket(over_ws) as socket:
            for first in range(0, 60, 20):
                assert socket.send_batch(batch(first, 20)) == client.send_batch(over_http, batch(first, 20))
            assert over_ws.last_seq == 3
            replay = socket.send_batch(batch(40, 20), seq=3)  # the last batch again: answered, not re-applied
            assert replay == client.send_batch(over_http, batch(40, 20), seq=3)
            with pytest.raises(Conflict) as conflict:
                socket.send_batch(batch(0, 20), seq=2)
            assert conflict.value.status == 409 and conflict.value.problems[0].field == "seq"
            with pytest.raises(
                InvalidRequest
            ) as invalid:  # an RSU the site does not have: refused by the server
                socket.send_batch([{"type": "rsu", "t": 3.0, "rsu_id": "NOPE", "range": 5.0, "bearing": 0.0}])
            assert invalid.value.status == 422 and invalid.value.problems[0].field.startswith(
                "measurements[0]"
            )
            socket._link.close()  # the link breaks between two batches: opened again, batch sent once
            assert len(socket.send_batch(batch(60, 20))) == 20
        info = client.get_session(over_ws)
        assert (info.last_seq, info.batches, info.epochs) == (4, 4, 80)


def test_refusals_reach_the_client_as_http_errors(server_url: str) -> None:
    with EdgeposClient(server_url, ADMIN_KEY, timeout=10.0, retries=0) as client:
        client.put_rsus(scenario_rsus())
        session = client.create_session("ws-refused", initial_state=INITIAL_STATE)
        stranger = Session(session.session_id, f"{session.session_id}.not-the-secret")
        with client.websocket(stranger) as socket, pytest.raises(Unauthorized):
            socket.send_batch(batch(0, 5))
        with client.websocket(session) as socket:
            socket.send_batch(batch(0, 5))
            newer = client.create_session("ws-refused", initial_state=INITIAL_STATE)
            with pytest.raises(Superseded) as superseded:
                socket.send_batch(batch(5, 5))
            assert newer.session_id in superseded.value.message
            with pytest.raises(
                Superseded
            ):  # the server closed the link (1008): the next batch is refused too
                socket.send_batch(batch(5, 5))


@pytest.mark.anyio
async def test_the_async_socket_sends_batches(server_url: str) -> None:
    async with AsyncEdgeposClient(server_url, ADMIN_KEY, timeout=10.0) as client:
        await client.put_rsus(scenario_rsus())
        session = await client.create_session("ws-async", initial_state=INITIAL_STATE)
        async with client.websocket(session) as socket:
            fixes = [fix for first in range(0, 40, 10) for fix in await socket.send_batch(batch(first, 10))]
            with pytest.raises(Conflict):
                await socket.send_batch(batch(0, 10), seq=1)
        assert len(fixes) == 40 and session.last_seq == 4
        assert abs(fixes[-1].x - 10.0 * 2.0) < 5.0  # 2 s at 10 m/s east, from the origin


def test_the_server_refuses_a_handshake_with_the_error_body_and_a_large_frame_with_1009(
    server_url: str,
) -> None:
    with EdgeposClient(server_url, ADMIN_KEY, timeout=10.0) as client:
        client.put_rsus(scenario_rsus())
        session = client.create_session("ws-raw", initial_state=INITIAL_STATE)
    with pytest.raises(InvalidStatus) as refused:
        connect(ws_url(server_url, session.session_id), additional_headers={"Authorization": "Bearer nope"})
    assert refused.value.response.status_code == 401
    assert json.loads(refused.value.response.body)["error"]["code"] == "unauthorized"
    bearer = {"Authorization": f"Bearer {session.token}"}
    with connect(ws_url(server_url, session.session_id), additional_headers=bearer, max_size=None) as link:
        link.send('{"seq": 1, "measurements": [' + " " * 2_000_000 + "]}")  # over the default 1 MiB
        with pytest.raises(ConnectionClosed) as closed:
            link.recv(10.0)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009


def test_a_link_the_server_closed_for_idling_is_opened_again_without_a_retry(tmp_path: Path) -> None:
    environment = clean_environment(
        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
        EDGEPOS_ADMIN_KEY_FILE=str(tmp_path / "admin.key"),
        EDGEPOS_WS_IDLE_TIMEOUT_S="0.5",
    )
    with (
        running(serve_command(1), environment, tmp_path / "server.log", ready_timeout_s=300.0) as url,
        EdgeposClient(url, ADMIN_KEY, timeout=10.0, retries=0) as client,
    ):
        client.put_rsus(scenario_rsus())
        session = client.create_session("ws-idle", initial_state=INITIAL_STATE)
        with client.websocket(session) as socket:
            socket.send_batch(batch(0, 5))
            deadline = time.monotonic() + 60.0
            while (
                socket._link.protocol.state is State.OPEN
            ):  # until the server has closed the idle link (1000)
                assert time.monotonic() < deadline, "the server did not close the idle link"
                time.sleep(0.05)
            assert len(socket.send_batch(batch(5, 5))) == 5  # retries=0: a new link, not a retry
        assert client.get_session(session).last_seq == 2
