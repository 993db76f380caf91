"""How a session record is laid out as a Redis hash (docs/redis.md, the key layout): its fields as bytes for
``HSET``, the record back from ``HGETALL`` or ``HMGET``, and a listing's summary from ``HMGET``."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence

from edgepos.store.base import SessionRecord, SessionSummary


def record_pairs(record: SessionRecord, version: int) -> list[tuple[bytes, bytes]]:
    """The record's hash fields as bytes (absent optional values are left out)."""
    pairs: list[tuple[str, str | bytes]] = [
        ("vehicle_id", record.vehicle_id),
        ("pipeline", record.pipeline),
        ("options", json.dumps(record.options, allow_nan=False)),
        ("token_hash", record.token_hash),
        ("state", bytes(record.state)),
        ("created_at", repr(float(record.created_at))),
        ("updated_at", repr(float(record.updated_at))),
        ("last_seq", str(int(record.last_seq))),
        ("batches", str(int(record.batches))),
        ("epochs", str(int(record.epochs))),
        ("version", str(int(version))),
    ]
    optional = (
        ("last_request_hash", record.last_request_hash),
        ("last_response", None if record.last_response is None else bytes(record.last_response)),
        ("last_fix", record.last_fix),
    )
    pairs.extend((name, value) for name, value in optional if value is not None)
    return [(name.encode(), value if isinstance(value, bytes) else value.encode()) for name, value in pairs]


def record_fields(record: SessionRecord, version: int) -> list[bytes]:
    """The record as a flat field/value list for HSET."""
    return [item for pair in record_pairs(record, version) for item in pair]


def record_from_hash(session_id: str, raw: Mapping[bytes, bytes]) -> SessionRecord:
    """A record from the hash HGETALL returned (keys and values are bytes)."""
    text = {key.decode(): value for key, value in raw.items()}

    def optional_text(name: str) -> str | None:
        value = text.get(name)
        return None if value is None else value.decode()

    return SessionRecord(
        session_id=session_id,
        vehicle_id=text["vehicle_id"].decode(),
        pipeline=text["pipeline"].decode(),
        options=json.loads(text["options"]),
        token_hash=text["token_hash"].decode(),
        state=bytes(text["state"]),
        created_at=float(text["created_at"]),
        updated_at=float(text["updated_at"]),
        last_seq=int(text["last_seq"]),
        last_request_hash=optional_text("last_request_hash"),
        last_response=text.get("last_response"),
        batches=int(text["batches"]),
        epochs=int(text["epochs"]),
        last_fix=optional_text("last_fix"),
        version=int(text["version"]),
    )


RECORD_FIELDS = (
    "vehicle_id", "pipeline", "options", "token_hash", "state", "created_at", "updated_at", "last_seq",
    "batches", "epochs", "version", "last_request_hash", "last_fix",
)  # fmt: skip
"""The hash fields of a record but its stored answer (``last_response``), for ``get(with_response=False)``."""

SUMMARY_FIELDS = (
    "vehicle_id", "pipeline", "created_at", "updated_at", "last_seq", "batches", "epochs", "last_fix"
)  # fmt: skip


def summary_from_fields(session_id: str, values: Sequence[bytes | None]) -> SessionSummary | None:
    """A summary from HMGET of :data:`SUMMARY_FIELDS`; None when the session hash is gone."""
    vehicle, pipeline, created, updated, last_seq, batches, epochs, last_fix = values
    if vehicle is None or pipeline is None or created is None or updated is None:
        return None
    return SessionSummary(
        session_id=session_id,
        vehicle_id=vehicle.decode(),
        pipeline=pipeline.decode(),
        created_at=float(created),
        updated_at=float(updated),
        last_seq=int(last_seq or 0),
        batches=int(batches or 0),
        epochs=int(epochs or 0),
        last_fix=None if last_fix is None else last_fix.decode(),
    )
