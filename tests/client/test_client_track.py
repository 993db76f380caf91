"""Late measurements and the window's track through the async client, against the real app in-process."""

from __future__ import annotations

import pytest
from clienthelp import INITIAL_STATE, batch
from edgepos_client import AsyncEdgeposClient, Track

pytestmark = pytest.mark.anyio


async def test_revised_fixes_and_the_track_through_the_client(aclient: AsyncEdgeposClient) -> None:
    session = await aclient.create_session("car-1", initial_state=INITIAL_STATE)
    await aclient.send_batch(session, batch(0, 20))
    held = [m for m in batch(20, 1) if m.type == "rsu"]
    now = await aclient.send_batch(session, [m for m in batch(20, 2) if m not in held])
    assert [fix.revised for fix in now] == [False, False]
    later = await aclient.send_batch(session, [*batch(22, 1), *held])
    assert [(fix.t, fix.revised) for fix in later] == [
        (now[0].t, True),
        (now[1].t, True),
        (later[-1].t, False),
    ]
    assert {m.index for m in later[0].measurements} == set(
        range(len(batch(22, 1)), len(batch(22, 1)) + len(held))
    )

    filtered = await aclient.track(session)
    smoothed = await aclient.track(session.session_id, smoothed=True)  # a bare id opens with the admin key
    assert isinstance(filtered, Track) and not filtered.smoothed and smoothed.smoothed
    assert filtered.end_t == later[-1].t and filtered.max_delay_s == 1.0
    assert [f.t for f in smoothed.fixes] == [f.t for f in filtered.fixes]
    assert filtered.fixes[-1].x == pytest.approx(later[-1].x, abs=1e-9)
    assert all(f.state is not None for f in smoothed.fixes)
