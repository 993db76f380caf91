"""The lag window's state: its dataclasses, its byte layout, and the observation records it keeps.

Layout: ``_HEADER`` (magic, version, the window's options, the newest epoch, table sizes), then the
checkpoint table (time of each checkpoint's last epoch, length), the checkpoint states, the current
inner state, the window's epoch times and end offsets, and each epoch's observations as one record
(``encode_epoch``: ``core.observation_codec``'s exact binary form; version 1 wrote JSON rows). A
batch in time order appends records as bytes and decodes none of the stored ones. Version 3 added the
pseudorange's optional ``doppler_hz``: a version-2 window's records are converted when it is read (its
pseudoranges without Doppler), so sessions stored before the upgrade go on.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Sequence
from typing import Any

from edgepos.core.observation_codec import (
    ObservationCodecError,
    decode_legacy_observations,
    decode_observations,
    encode_observations,
)
from edgepos.core.observations import Observation
from edgepos.core.state import StateFormatError

MAGIC = b"EPLW"
VERSION = 3
_CONVERTIBLE = (2,)
"""Older versions whose records ``_unpack`` converts to this version's layout."""

# magic, version, max_delay_s, max_window_epochs, max_lead_s, newest epoch (NaN: none), checkpoints,
# current state length, observations.
_HEADER = struct.Struct("<4sBdIddIII")
_CHECKPOINT = struct.Struct("<dI")  # time of the state's last epoch (NaN: none), state length
_NAN = math.nan


# -- the observation codec ---------------------------------------------------------------------------
def encode_epoch(observations: Sequence[Observation]) -> bytes:
    """An epoch's observations as one record (``core.observation_codec``: exact, compact binary)."""
    return encode_observations(observations)


def decode_epoch(record: bytes) -> list[Observation]:
    try:
        return decode_observations(record)
    except ObservationCodecError as error:
        raise StateFormatError(f"lag window record does not decode: {error}") from None


def _convert(record: bytes, version: int) -> bytes:
    """A record of an older window version in this version's layout."""
    try:
        return encode_observations(decode_legacy_observations(record, version))
    except ObservationCodecError as error:
        raise StateFormatError(f"lag window record (version {version}) does not decode: {error}") from None


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
        if version != VERSION and version not in _CONVERTIBLE:
            raise StateFormatError(
                f"lag window version {version} is not {VERSION} (nor one it converts): open a new session"
            )
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
    if version != VERSION:
        records = [_convert(record, version) for record in records]
    options = {"max_delay_s": delay, "max_window_epochs": epochs, "max_lead_s": lead}
    return _Window(
        options, None if math.isnan(newest) else newest, stored, current, list(index[:count]), records
    )
