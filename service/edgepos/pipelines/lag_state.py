"""The lag window's state: its dataclasses, its byte layout, and the observation records it keeps.

Layout: ``_HEADER`` (magic, version, the window's options, the newest epoch, table sizes), then the
checkpoint table (time of each checkpoint's last epoch, length), the checkpoint states, the current
inner state, the window's epoch times and end offsets, and each epoch's observations as one JSON
record (``encode_epoch``: kind, then the fields in declaration order). Exact: floats are written by
Python's shortest round-tripping repr. A batch in time order appends records as bytes and decodes
none of the stored ones.
"""

from __future__ import annotations

import dataclasses
import json
import math
import operator
import struct
import typing
from collections.abc import Callable, Sequence
from typing import Any

from edgepos.core.observations import Observation
from edgepos.core.state import StateFormatError

MAGIC = b"EPLW"
VERSION = 1

# magic, version, max_delay_s, max_window_epochs, max_lead_s, newest epoch (NaN: none), checkpoints,
# current state length, observations.
_HEADER = struct.Struct("<4sBdIddIII")
_CHECKPOINT = struct.Struct("<dI")  # time of the state's last epoch (NaN: none), state length
_NAN = math.nan

# Observation kinds by wire name, from the union in core.observations (a new kind registers there).
_KINDS: dict[str, type] = {cls.kind: cls for cls in typing.get_args(Observation)}


# -- the observation codec ---------------------------------------------------------------------------
# Each kind's row: its wire name, then its fields in declaration order (one attrgetter call per observation).
_ROW: dict[type, Callable[[Any], tuple[Any, ...]]] = {
    cls: operator.attrgetter("kind", *(f.name for f in dataclasses.fields(cls))) for cls in _KINDS.values()
}
# Built once: json.dumps with non-default arguments builds a new encoder on every call.
_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


def encode_epoch(observations: Sequence[Observation]) -> bytes:
    """An epoch's observations as one compact JSON array of arrays: kind, then the fields in declaration
    order (one encoder call per epoch, not per observation)."""
    return _ENCODER.encode([_ROW[type(o)](o) for o in observations]).encode()


def decode_epoch(record: bytes) -> list[Observation]:
    try:
        rows = json.loads(record)
    except ValueError as error:
        raise StateFormatError(f"lag window record does not decode: {error}") from None
    observations = []
    for values in rows if isinstance(rows, list) else [None]:
        cls = _KINDS.get(values[0]) if isinstance(values, list) and values else None
        if cls is None:
            raise StateFormatError("lag window holds an unknown observation kind")
        fields = [tuple(v) if isinstance(v, list) else v for v in values[1:]]
        try:
            observations.append(typing.cast(Observation, cls(*fields)))
        except TypeError as error:
            raise StateFormatError(f"lag window observation does not decode: {error}") from None
    return observations


# -- the window's state --------------------------------------------------------------------------------------
@dataclasses.dataclass
class _Checkpoint:
    t: float | None  # the time of the last epoch filtered into ``state`` (None: none yet)
    state: bytes


@dataclasses.dataclass
class _Window:
    options: dict[str, Any]
    newest: float | None  # the session's newest epoch
    checkpoints: list[_Checkpoint]  # oldest first; [0] is the base
    current: bytes  # the inner state after every observation of the window
    times: list[float]  # the window's epochs (distinct observation times), ascending
    records: list[bytes]  # each epoch's observations (``encode_epoch``), same order

    @property
    def base(self) -> _Checkpoint:
        return self.checkpoints[0]

    def observations(self, start: int = 0) -> list[Observation]:
        """The observations of the window's epochs from ``start`` on, in time order."""
        return [o for record in self.records[start:] for o in decode_epoch(record)]


def _pack(window: _Window) -> bytes:
    options = window.options
    header = _HEADER.pack(
        MAGIC,
        VERSION,
        float(options["max_delay_s"]),
        int(options["max_window_epochs"]),
        float(options["max_lead_s"]),
        _NAN if window.newest is None else window.newest,
        len(window.checkpoints),
        len(window.current),
        len(window.records),
    )
    parts = [header]
    parts += [_CHECKPOINT.pack(_NAN if c.t is None else c.t, len(c.state)) for c in window.checkpoints]
    parts += [c.state for c in window.checkpoints]
    parts.append(window.current)
    count = len(window.records)
    ends, end = [], 0
    for record in window.records:
        end += len(record)
        ends.append(end)
    parts.append(struct.pack(f"<{count}d{count}I", *window.times, *ends))
    parts += window.records
    return b"".join(parts)


def newest_epoch(state: bytes) -> float | None:
    """The window's newest epoch from its header alone (None: none yet, or not a readable window)."""
    if state[: len(MAGIC)] != MAGIC or len(state) < _HEADER.size:
        return None
    newest = _HEADER.unpack_from(state)[5]
    return None if math.isnan(newest) else newest


def _unpack(state: bytes) -> _Window:
    if state[: len(MAGIC)] != MAGIC:
        raise StateFormatError("state has no lag window (written by an older edgepos): open a new session")
    try:
        _, version, delay, epochs, lead, newest, checkpoints, current_length, count = _HEADER.unpack_from(
            state
        )
        if version != VERSION:
            raise StateFormatError(f"lag window version {version} is not {VERSION}")
        offset = _HEADER.size
        table = [_CHECKPOINT.unpack_from(state, offset + i * _CHECKPOINT.size) for i in range(checkpoints)]
        offset += checkpoints * _CHECKPOINT.size
        stored = []
        for t, length in table:
            stored.append(_Checkpoint(None if math.isnan(t) else t, state[offset : offset + length]))
            offset += length
        current = state[offset : offset + current_length]
        offset += current_length
        index = struct.unpack_from(f"<{count}d{count}I", state, offset)
        offset += count * 12
        records, start = [], 0
        for end in index[count:]:
            records.append(state[offset + start : offset + end])
            start = end
        if offset + start != len(state) or not stored or len(current) != current_length:
            raise StateFormatError("lag window is truncated or corrupt")
    except struct.error as error:
        raise StateFormatError(f"lag window is truncated: {error}") from None
    options = {"max_delay_s": delay, "max_window_epochs": epochs, "max_lead_s": lead}
    return _Window(
        options, None if math.isnan(newest) else newest, stored, current, list(index[:count]), records
    )
