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
import itertools
import math
import struct
from collections.abc import Sequence
from typing import Any

from edgepos.core.observation_codec import (
    ObservationCodecError,
    decode_legacy_observations,
    decode_observations,
    encode_each,
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


def encode_epochs(observations: Sequence[Observation], counts: Sequence[int]) -> list[bytes]:
    """The records of consecutive epochs of ``observations``, ``counts[k]`` observations in epoch ``k``
    (``encode_epoch`` of each, from one pass over the observations)."""
    each = encode_each(observations)
    records = []
    start = 0
    for count in counts:
        records.append(each[start] if count == 1 else b"".join(each[start : start + count]))
        start += count
    return records


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
    return _pack_parts(
        (float(options["max_delay_s"]), int(options["max_window_epochs"]), float(options["max_lead_s"])),
        window.newest,
        [(c.t, c.state) for c in window.checkpoints],
        window.current,
        window.times,
        list(itertools.accumulate(len(record) for record in window.records)),
        window.records,
    )


def _pack_parts(
    options: tuple[float, int, float],
    newest: float | None,
    checkpoints: Sequence[tuple[float | None, bytes | memoryview]],
    current: bytes | memoryview,
    times: Sequence[float],
    ends: Sequence[int],
    records: Sequence[bytes | memoryview],
) -> bytes:
    """The window's bytes from its parts: ``options`` (max_delay_s, max_window_epochs, max_lead_s), the
    checkpoints as (t, state), the epochs' times and the end offsets of their records, and the records'
    bytes back to back in one or more pieces (``_pack`` gives one per epoch, the in-order path of
    ``lag`` the kept stored ones as one piece)."""
    delay, epochs, lead = options
    count = len(times)
    parts: list[bytes | memoryview] = [
        _HEADER.pack(
            MAGIC,
            VERSION,
            delay,
            epochs,
            lead,
            _NAN if newest is None else newest,
            len(checkpoints),
            len(current),
            count,
        )
    ]
    parts += [_CHECKPOINT.pack(_NAN if t is None else t, len(state)) for t, state in checkpoints]
    parts += [state for _, state in checkpoints]
    parts.append(current)
    parts.append(struct.pack(f"<{count}d{count}I", *times, *ends))
    parts += records
    return b"".join(parts)


@dataclasses.dataclass
class _Spans:
    """Where a window's parts lie in its bytes, read from the header and tables alone (no checkpoint,
    state or record copied or decoded): what a batch in time order needs (``lag``'s in-order path)."""

    options: tuple[float, int, float]  # max_delay_s, max_window_epochs, max_lead_s
    newest: float | None
    checkpoint_times: list[float | None]
    checkpoint_states: list[memoryview]
    current: memoryview
    times: list[float]
    ends: list[int]  # each epoch record's end, from the start of the records
    records: memoryview  # every record, back to back


def _spans(state: bytes) -> _Spans | None:
    """The spans of a window of this version; None for anything else (an older version, damage: the
    full ``_unpack`` converts or refuses it)."""
    if state[: len(MAGIC)] != MAGIC or len(state) < _HEADER.size:
        return None
    _, version, delay, epochs, lead, newest, checkpoints, current_length, count = _HEADER.unpack_from(state)
    if version != VERSION:
        return None
    view = memoryview(state)
    offset = _HEADER.size
    try:
        table = struct.unpack_from("<" + "dI" * checkpoints, state, offset)
        offset += checkpoints * _CHECKPOINT.size
        checkpoint_times: list[float | None] = []
        checkpoint_states = []
        for t, length in zip(table[0::2], table[1::2], strict=True):
            checkpoint_times.append(None if math.isnan(t) else t)
            checkpoint_states.append(view[offset : offset + length])
            offset += length
        current = view[offset : offset + current_length]
        offset += current_length
        index = struct.unpack_from(f"<{count}d{count}I", state, offset)
    except struct.error:
        return None
    offset += count * 12
    ends = list(index[count:])
    if not checkpoints or offset + (ends[-1] if ends else 0) != len(state) or len(current) != current_length:
        return None
    return _Spans(
        (delay, epochs, lead),
        None if math.isnan(newest) else newest,
        checkpoint_times,
        checkpoint_states,
        current,
        list(index[:count]),
        ends,
        view[offset:],
    )


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
