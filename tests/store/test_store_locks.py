"""Per-session locks: one holder per session at a time, independent sessions, no leak."""

from __future__ import annotations

import asyncio

from edgepos.store.base import SessionLocks


def test_same_session_is_serialised_and_others_are_not():
    async def scenario() -> list[str]:
        locks = SessionLocks()
        events: list[str] = []

        async def hold(session_id: str, name: str) -> None:
            async with locks.hold(session_id):
                events.append(f"{name}+")
                await asyncio.sleep(0.01)
                events.append(f"{name}-")

        await asyncio.gather(hold("s", "a"), hold("s", "b"), hold("t", "c"))
        assert len(locks) == 0  # nothing kept once nobody holds or waits
        return events

    events = asyncio.run(scenario())
    a, b = events.index("a+"), events.index("b+")
    first, second = ("a", "b") if a < b else ("b", "a")
    assert events.index(f"{first}-") < events.index(f"{second}+")
    assert events.index("c+") < events.index(f"{first}-")  # another session ran alongside


def test_lock_is_released_when_the_holder_fails():
    async def scenario() -> int:
        locks = SessionLocks()
        try:
            async with locks.hold("s"):
                raise RuntimeError("boom")
        except RuntimeError:
            pass
        async with locks.hold("s"):
            pass
        return len(locks)

    assert asyncio.run(scenario()) == 0
