"""How the fix stream's events are laid out in its Redis stream (docs/redis.md, "The fix stream"): one
stream entry per run of consecutive fixes of one session, which is a batch's fixes in practice, rather
than one entry per fix.

Appending a batch's twenty fixes as twenty entries took twenty ``XADD`` calls inside the batch's script,
each with its own call, propagation to the append-only file and trimming, and this was about two thirds
of redis-server's CPU for the batch (docs/benchmarks.md, "fixbatch"). An entry keeps its fixes' ids
dense: its stream id is the id of its last fix, and it holds ``n`` fixes, so its first fix's id is
``last - n + 1``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from edgepos.store.fixlog import FixEvent, NewFix

FIXES_PER_ENTRY = 100
"""The most fixes one entry holds. The stream is trimmed by whole entries, so it holds at most this many
minus one fixes beyond its buffer."""

ARGUMENTS_PER_ENTRY = 7
"""What the scripts take for each entry (``APPEND_FIXES_FN``): session id, vehicle id, pipeline, the
number of fixes, their times, their data's lengths and their data joined."""


def fix_arguments(fixes: Sequence[NewFix]) -> list[str | bytes]:
    """The fixes as the fix stream's scripts take them, ``ARGUMENTS_PER_ENTRY`` values for each entry: a
    run of consecutive fixes of one session (at most ``FIXES_PER_ENTRY``). Times are written with
    ``repr`` (exact) and separated by spaces, as the lengths of the data are."""
    arguments: list[str | bytes] = []
    start, count = 0, len(fixes)
    while start < count:
        head = fixes[start]
        whose = (head.session_id, head.vehicle_id, head.pipeline)
        end, limit = start + 1, min(count, start + FIXES_PER_ENTRY)
        while end < limit and (fixes[end].session_id, fixes[end].vehicle_id, fixes[end].pipeline) == whose:
            end += 1
        run = fixes[start:end]
        arguments += (
            *whose,
            str(len(run)),
            " ".join([repr(float(fix.t)) for fix in run]),
            " ".join([str(len(fix.data)) for fix in run]),
            b"".join([fix.data for fix in run]),
        )
        start = end
    return arguments


def entry_size(fields: Mapping[bytes, bytes]) -> int:
    """How many fixes an entry holds."""
    return int(fields[b"n"])


def entry_events(entry_id: bytes | str, fields: Mapping[bytes, bytes]) -> list[FixEvent]:
    """The fix events an entry holds, oldest first. ValueError if the entry is not one of this layout
    (its times or lengths do not match its count, or its data is longer or shorter than their sum)."""
    text = entry_id.decode() if isinstance(entry_id, bytes) else entry_id
    count = entry_size(fields)
    times, lengths, data = fields[b"t"].split(), fields[b"l"].split(), fields[b"d"]
    if len(times) != count or len(lengths) != count:
        raise ValueError(f"fix stream entry {text} says {count} fixes but holds {len(times)} times")
    session_id, vehicle_id, pipeline = fields[b"s"].decode(), fields[b"v"].decode(), fields[b"p"].decode()
    first = int(text.partition("-")[0]) - count + 1
    events, offset = [], 0
    for index in range(count):
        end = offset + int(lengths[index])
        events.append(
            FixEvent(
                first + index, session_id, vehicle_id, pipeline, float(times[index]), bytes(data[offset:end])
            )
        )
        offset = end
    if offset != len(data):
        raise ValueError(f"fix stream entry {text}'s data is not the sum of its fixes' lengths")
    return events
