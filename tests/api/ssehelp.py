"""Reading server-sent events in the stream tests: from the lines of a streamed response, event by event."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any


@dataclass
class Event:
    """One server-sent event; ``event`` is ``ping`` for a keep-alive comment."""

    event: str
    data: str = ""
    id: str | None = None

    def json(self) -> Any:
        return json.loads(self.data)


def events(lines: Iterator[str]) -> Iterator[Event]:
    """The events of an SSE body, keep-alive comments as ``ping`` events (other comments skipped)."""
    fields: dict[str, str] = {}
    for line in lines:
        if line == "":
            if "event" in fields or "data" in fields:
                yield Event(fields.get("event", "message"), fields.get("data", ""), fields.get("id"))
            fields = {}
        elif line.startswith(":"):
            if line.strip() == ": ping":
                yield Event("ping")
        else:
            name, _, value = line.partition(":")
            fields[name] = value.removeprefix(" ")


def take(
    stream: Iterator[Event], fixes: int, *, max_pings: int = 20, until: str | None = None
) -> list[Event]:
    """Events until ``fixes`` fix events arrived (or an ``until`` event), or ``max_pings`` pings came
    first (so a test whose events never come fails instead of hanging). Pings are left out."""
    found: list[Event] = []
    pings = 0
    for event in stream:
        if event.event == "ping":
            pings += 1
            if pings >= max_pings:
                break
            continue
        found.append(event)
        if until is not None and event.event == until:
            break
        if until is None and sum(e.event == "fix" for e in found) >= fixes:
            break
    return found


def until_ping(stream: Iterator[Event]) -> list[Event]:
    """Every event before the next keep-alive ping: what the stream had to send while it was busy."""
    found = []
    for event in stream:
        if event.event == "ping":
            return found
        found.append(event)
    return found
