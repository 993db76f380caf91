"""The record a batch writes: built as a copy of the stored record's fields, it must be exactly what
``dataclasses.replace`` gives (``session_service._applied``)."""

from __future__ import annotations

import dataclasses

import pytest
from edgepos.api.session_service import _applied
from edgepos.store.base import SessionRecord


def test_a_batch_applied_gives_the_record_dataclasses_replace_gives():
    assert not hasattr(SessionRecord, "__post_init__")
    assert all(field.init for field in dataclasses.fields(SessionRecord))
    record = SessionRecord(
        session_id="a" * 32,
        vehicle_id="car-1",
        pipeline="rsu_imu",
        options={"filter": "ckf", "models": ["ca", "at"]},
        token_hash="b" * 64,
        state=b"old state",
        created_at=100.0,
        updated_at=101.5,
        last_seq=7,
        last_request_hash="c" * 64,
        last_response=b'{"seq":7,"fixes":[]}',
        batches=7,
        epochs=130,
        last_fix='{"t":6.95}',
        version=9,
    )
    applied = _applied(
        record, state=b"new state", seq=8, digest="d" * 64, body=b"{}", epochs=3, last_fix=None, now=102.0
    )
    assert type(applied) is SessionRecord and applied is not record
    assert applied == dataclasses.replace(
        record,
        state=b"new state",
        last_seq=8,
        last_request_hash="d" * 64,
        last_response=b"{}",
        batches=8,
        epochs=133,
        last_fix=None,
        updated_at=102.0,
    )
    assert applied.options is record.options and applied.version == 9  # as replace: shared, unchanged
    assert record.last_seq == 7 and record.state == b"old state"
    with pytest.raises(dataclasses.FrozenInstanceError):
        applied.version = 10  # type: ignore[misc]
