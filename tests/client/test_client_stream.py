"""``stream_fixes`` of both clients against a real server over a loopback socket: the fixes of applied
batches as typed events, live and resumed with Last-Event-ID, filtered to one vehicle, with a session's
own token, and the server's refusals as typed errors."""

from __future__ import annotations

import itertools

import pytest
from clienthelp import ADMIN_KEY, INITIAL_STATE, batch, scenario_rsus
from edgepos_client import AsyncEdgeposClient, EdgeposClient, FixEvent, InvalidRequest, StreamNotice

pytestmark = pytest.mark.slow


def _fix_events(items: list[FixEvent | StreamNotice]) -> list[FixEvent]:
    return [item for item in items if isinstance(item, FixEvent)]


def test_sync_stream_resumes_and_follows_live_fixes(server_url: str) -> None:
    with EdgeposClient(server_url, ADMIN_KEY, timeout=10.0) as client:
        client.put_rsus(scenario_rsus())
        session = client.create_session("stream-sync-car", initial_state=INITIAL_STATE)
        first = client.send_batch(session, batch(0, 3))
        # from the start of the buffer, this vehicle only: the batch sent before the stream opened
        stream = client.stream_fixes(vehicle_ids=["stream-sync-car"], last_event_id="0")
        got = _fix_events(list(itertools.islice(stream, 3)))
        assert [event.fix for event in got] == first
        assert {(event.vehicle_id, event.session_id, event.seq, event.pipeline) for event in got} == {
            ("stream-sync-car", session.session_id, 1, "rsu_imu")
        }
        second = client.send_batch(session, batch(3, 2))  # live, while the stream is open
        live = _fix_events(list(itertools.islice(stream, 2)))
        assert [event.fix for event in live] == second
        stream.close()
        ids = [int(event.id) for event in got + live]
        assert ids == sorted(ids) and len(set(ids)) == 5
        # resumed after the first batch's last fix: exactly the second batch
        resumed = client.stream_fixes(vehicle_ids=["stream-sync-car"], last_event_id=got[-1].id)
        again = _fix_events(list(itertools.islice(resumed, 2)))
        resumed.close()
        assert [event.id for event in again] == [event.id for event in live]
        with pytest.raises(InvalidRequest):
            next(client.stream_fixes(pipelines=["no_such_pipeline"]))


@pytest.mark.anyio
async def test_async_stream_with_a_session_token(server_url: str) -> None:
    async with AsyncEdgeposClient(server_url, ADMIN_KEY, timeout=10.0) as client:
        await client.put_rsus(scenario_rsus())
        session = await client.create_session("stream-async-car", initial_state=INITIAL_STATE)
        other = await client.create_session("stream-async-other", initial_state=INITIAL_STATE)
        await client.send_batch(other, batch(0, 2))
        sent = await client.send_batch(session, batch(0, 4))
        received: list[FixEvent] = []
        stream = client.stream_fixes(session, last_event_id="0")  # the session's own token: its fixes only
        async for item in stream:
            assert isinstance(item, FixEvent)
            received.append(item)
            if len(received) == 4:
                break
        await stream.aclose()
        assert {event.session_id for event in received} == {session.session_id}
        assert [event.fix for event in received] == sent
