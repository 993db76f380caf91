"""Exact, self-describing serialisation of filter state: named float64 arrays plus JSON metadata.

Layout: b"EPST" | version byte | 4-byte little-endian header length | UTF-8 JSON header | the arrays'
raw little-endian float64 bytes, back to back. The header holds the metadata and each array's name
and shape. Arrays round-trip bit for bit; JSON numbers round-trip exactly because Python writes the
shortest repr that reads back to the same double. Non-finite numbers are refused: a state holding
NaN is a bug to surface, never something to store.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping
from typing import Any

import numpy as np

MAGIC = b"EPST"
VERSION = 1
_HEADER = struct.Struct("<4sBI")


class StateFormatError(ValueError):
    """Bytes that are not a state this version of edgepos wrote."""


# Built once: json.dumps with non-default arguments builds a new encoder on every call.
_JSON = json.JSONEncoder(allow_nan=False, separators=(",", ":"))


def pack(meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> bytes:
    """Serialise ``meta`` (JSON-able) and named float64 ``arrays``."""
    layout = []
    chunks = []
    for name, array in arrays.items():
        data = np.asarray(array, dtype="<f8")
        layout.append([name, list(data.shape)])
        chunks.append(data.tobytes())
    body = b"".join(chunks)
    if not np.isfinite(np.frombuffer(body, dtype="<f8")).all():  # one check over every array
        bad = next(name for name, array in arrays.items() if not np.all(np.isfinite(array)))
        raise ValueError(f"state array {bad!r} is not finite")
    encoded = _JSON.encode({"meta": meta, "arrays": layout}).encode()
    return _HEADER.pack(MAGIC, VERSION, len(encoded)) + encoded + body


def unpack(blob: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Inverse of :func:`pack`."""
    if len(blob) < _HEADER.size:
        raise StateFormatError("state is truncated")
    magic, version, header_length = _HEADER.unpack_from(blob)
    if magic != MAGIC or version != VERSION:
        raise StateFormatError(f"not an edgepos state (magic {magic!r}, version {version})")
    start = _HEADER.size
    try:
        header = json.loads(blob[start : start + header_length])
        meta, layout = header["meta"], header["arrays"]
        shapes = [(str(name), tuple(int(n) for n in shape)) for name, shape in layout]
    except (ValueError, KeyError, TypeError) as error:
        raise StateFormatError(f"state header is corrupt: {error!r}") from None
    if not isinstance(meta, dict) or any(n < 0 for _, shape in shapes for n in shape):
        raise StateFormatError("state header is corrupt")
    offset = start + header_length
    counts = [math.prod(shape) for _, shape in shapes]
    total = sum(counts)
    if offset + 8 * total != len(blob):
        raise StateFormatError(
            "state is truncated" if offset + 8 * total > len(blob) else "state has trailing bytes"
        )
    values = np.frombuffer(blob, dtype="<f8", count=total, offset=offset).astype(float)  # one writable copy
    arrays: dict[str, np.ndarray] = {}
    position = 0
    for (name, shape), count in zip(shapes, counts, strict=True):
        arrays[name] = values[position : position + count].reshape(shape)
        position += count
    return meta, arrays
