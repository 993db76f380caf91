"""What a worker of the Redis store keeps between batches so that a batch costs one round trip: the session
records it wrote last (an LRU bounded by count) and the RSU map with the token of its last write.

Neither is trusted on its own. A cached record is only the base a batch is computed on: the batch's
compare-and-set applies only while the stored version is still the cached one, so a record another worker
wrote, or a session deleted, superseded, revoked or expired meanwhile (each removes the hash), fails the
write and the batch is redone on a fresh read. A cached RSU map is sent back as its token with the write,
which the script compares with the stored token (set afresh by every RSU write) in the same atomic step.
See docs/redis.md, "One round trip per batch"."""

from __future__ import annotations

import contextvars
import dataclasses
from collections import OrderedDict
from collections.abc import Mapping

from edgepos.pipelines.base import Rsu
from edgepos.store.base import SessionRecord

DEFAULT_RECORD_CACHE = 2048
"""Session records a worker keeps (``record_cache`` in the store URL; 0 turns the cache off). A record is
its state without the stored answer: about 20 kB for ``rsu_imu``, so some 40 MB per worker at most."""


class RecordCache:
    """The records this worker wrote last, by session id, the least recently used dropped beyond ``size``."""

    def __init__(self, size: int) -> None:
        if size < 0:
            raise ValueError(f"record_cache must be >= 0, got {size}")
        self.size = size
        self._records: OrderedDict[str, SessionRecord] = OrderedDict()

    def __len__(self) -> int:
        return len(self._records)

    def get(self, session_id: str) -> SessionRecord | None:
        record = self._records.get(session_id)
        if record is not None:
            self._records.move_to_end(session_id)
        return record

    def put(self, record: SessionRecord, version: int) -> None:
        """Keep ``record`` as stored under ``version``, without its stored answer (a replay reads afresh)."""
        if self.size == 0:
            return
        self._records[record.session_id] = dataclasses.replace(record, version=version, last_response=None)
        self._records.move_to_end(record.session_id)
        while len(self._records) > self.size:
            self._records.popitem(last=False)

    def drop(self, session_id: str) -> None:
        self._records.pop(session_id, None)


class RsuSnapshot:
    """The RSU map as read with the token of the write that made it (``""``: never written with a token)."""

    def __init__(self, token: str, rsus: Mapping[str, Rsu]) -> None:
        self.token = token
        self.rsus = dict(rsus)


RSUS_USED: contextvars.ContextVar[str | None] = contextvars.ContextVar("edgepos_rsus_used", default=None)
"""The token of the RSU snapshot the current request's batch was computed on (set by ``get_rsus``, sent
and cleared by ``compare_and_set``): each request runs in a task of its own, so in a context of its own."""
