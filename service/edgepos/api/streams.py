"""The fix stream (``GET /v1/stream/fixes``): server-sent events of every applied fix.

One :class:`StreamHub` per worker. Publishing: an applied batch hands its fixes to :meth:`StreamHub.publish`,
which only appends them to this worker's outbox and returns; one publisher task writes the outbox to the
store's fix log (``edgepos.store.fixlog``: a Redis stream or a SQLite table), so the vehicle's answer never
waits for the stream and a store that is slow to take the stream writes costs fixes on the stream
(counted), never batch latency. The in-process store's log, in this process's memory, takes them at once. Consuming: one reader task per worker, running while
the worker has consumers, reads the log (XREAD BLOCK on a connection of its own on Redis) and offers
each event to every consumer's bounded queue, without ever awaiting a consumer: a consumer whose queue
is full is dropped with a final ``end`` event (it resumes with ``Last-Event-ID``). Filters apply when an
event is offered, decimation (``max_rate_hz``) when it is sent, in id order.
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass, field

from edgepos.api.convert import to_json
from edgepos.api.errors import ApiError
from edgepos.api.metrics import Metrics
from edgepos.store.base import StoreUnavailable
from edgepos.store.fixlog import FixEvent, FixLog, Gap, NewFix

logger = logging.getLogger("edgepos.api")

MAX_RATE_HZ = 100.0
"""Largest max_rate_hz a consumer may ask for (no pipeline produces fixes faster)."""
READ_BLOCK_S = 1.0
"""How long the reader waits for new events in one read (it notices that its last consumer left within this)."""
READ_COUNT = 1000
PUBLISH_CHUNK = 500
"""Fixes per write to the log (the publisher coalesces what batches left in the outbox meanwhile)."""
OUTBOX_LIMIT = 20_000
"""Fixes a worker's outbox may hold while the store is slow to take them; beyond, new ones are dropped."""
SEND_CHUNK = 256
"""Events one write to a consumer carries at most: a burst of fixes goes out in a few writes, not one each."""
_TOLERANCE_S = 1e-6


def fix_event_prefix(session_id: str, vehicle_id: str, pipeline: str, seq: int) -> bytes:
    """The JSON of a ``fix`` event (:class:`FixEventOut`) up to its fix: the same for every fix of a batch,
    so written once per batch (:func:`fix_event_data`)."""
    head = to_json({"session_id": session_id, "vehicle_id": vehicle_id, "pipeline": pipeline, "seq": seq})
    return head[:-1] + b',"fix":'


def fix_event_data(prefix: bytes, fix_json: bytes) -> bytes:
    """The JSON of a ``fix`` event around a wire fix's compact JSON with a null ``state`` (already written for
    the batch's answer), after the batch's :func:`fix_event_prefix`: the bytes of ``to_json`` of the whole
    event."""
    return prefix + fix_json + b"}"


def sse(event: str, data: bytes, event_id: int | None = None) -> bytes:
    """One server-sent event (the data is compact JSON: one line)."""
    head = b"" if event_id is None else b"id: %d\n" % event_id
    return head + b"event: " + event.encode() + b"\ndata: " + data + b"\n\n"


@dataclass(frozen=True)
class StreamFilter:
    """Which fixes a consumer gets: None means any."""

    session_id: str | None = None
    pipelines: frozenset[str] | None = None
    vehicles: frozenset[str] | None = None

    def matches(self, event: FixEvent) -> bool:
        return (
            (self.session_id is None or event.session_id == self.session_id)
            and (self.pipelines is None or event.pipeline in self.pipelines)
            and (self.vehicles is None or event.vehicle_id in self.vehicles)
        )


@dataclass(eq=False)  # compared (and hashed) by identity: the hub keeps a set of them
class Consumer:
    """One connected stream: its filter and bounded queue (events, or a Gap when the reader fell behind)."""

    filter: StreamFilter
    limit: int
    queue: deque[FixEvent | Gap] = field(default_factory=deque)
    dropped: bool = False
    _ready: asyncio.Event = field(default_factory=asyncio.Event)

    def offer(self, event: FixEvent | Gap) -> bool:
        """Queue the event if it passes the filter; False when the queue is full (the consumer is dropped)."""
        if self.dropped:
            return True
        if isinstance(event, FixEvent) and not self.filter.matches(event):
            return True
        if len(self.queue) >= self.limit:
            return False
        self.queue.append(event)
        self._ready.set()
        return True

    def drop(self) -> int:
        """Mark dropped and empty the queue; returns how many queued events were lost."""
        lost = len(self.queue)
        self.queue.clear()
        self.dropped = True
        self._ready.set()
        return lost

    async def take(self, timeout_s: float, most: int) -> list[FixEvent | Gap]:
        """Up to ``most`` queued events, waiting up to ``timeout_s`` for one; empty after that or once dropped."""
        while not self.queue:
            if self.dropped:
                return []
            self._ready.clear()
            try:
                await asyncio.wait_for(self._ready.wait(), timeout_s)
            except TimeoutError:
                return []
        queue = self.queue
        return [queue.popleft() for _ in range(min(most, len(queue)))]


class StreamHub:
    """This worker's side of the fix stream: the publisher, the reader and the connected consumers."""

    def __init__(
        self,
        log: FixLog,
        metrics: Metrics,
        *,
        queue: int,
        max_consumers: int,
        ping_s: float,
        interval_s: float = 0.05,
    ) -> None:
        self.log = log
        self.interval_s = interval_s
        self.metrics = metrics
        self.queue = queue
        self.max_consumers = max_consumers
        self.ping_s = ping_s
        self._outbox: deque[NewFix] = deque()
        self._publisher: asyncio.Task[None] | None = None
        self._consumers: set[Consumer] = set()
        self._reader: asyncio.Task[None] | None = None
        self._starting: asyncio.Lock | None = None
        self._cursor = 0

    # publishing ---------------------------------------------------------------------------------
    def publish(self, fixes: Sequence[NewFix]) -> None:
        """Hand the fixes of an applied batch to the publisher; never waits. The in-process store's log
        takes them at once (a deque in this process: a publisher task per batch cost more than the append)."""
        if not fixes:
            return
        if self.log.append_now(fixes):  # a log in this process's memory takes them at once
            return
        if len(self._outbox) + len(fixes) > OUTBOX_LIMIT:
            self.metrics.stream_events_dropped.labels("publish_backlog").inc(len(fixes))
            return
        self._outbox.extend(fixes)
        if self._publisher is None or self._publisher.done():
            self._publisher = asyncio.get_running_loop().create_task(self._publish_all())

    async def _publish_all(self) -> None:
        while self._outbox:
            chunk = [self._outbox.popleft() for _ in range(min(PUBLISH_CHUNK, len(self._outbox)))]
            try:
                await self.log.append(chunk)
            except Exception as error:  # noqa: BLE001 - the batches are applied: only the stream loses these fixes
                self.metrics.stream_events_dropped.labels("store_unavailable").inc(len(chunk))
                logger.warning(
                    "fixes not published on the stream",
                    extra={"event": "stream_publish_failed", "count": len(chunk), "error": str(error)},
                )

    async def flush(self) -> None:
        """Wait until the outbox is written (tests; shutdown)."""
        while self._publisher is not None and not self._publisher.done():
            await asyncio.shield(self._publisher)

    # consuming ----------------------------------------------------------------------------------
    @property
    def consumer_count(self) -> int:
        """Consumers connected to this worker now."""
        return len(self._consumers)

    async def subscribe(
        self, stream_filter: StreamFilter, after: int | None
    ) -> tuple[Consumer, list[FixEvent], Gap | None]:
        """A new consumer, and (resuming after ``after``) the held events it missed and the gap if any."""
        if len(self._consumers) >= self.max_consumers:
            raise ApiError(
                "unavailable",
                f"this worker already serves its maximum of {self.max_consumers} fix streams "
                "(EDGEPOS_STREAM_MAX_CONSUMERS); retry later",
                headers={"Retry-After": "5"},
            )
        consumer = Consumer(stream_filter, self.queue)
        self._consumers.add(consumer)
        try:
            await self._start_reader()  # before the backlog is read: no event falls between the two
            backlog, gap = ([], None) if after is None else await self.log.backlog(after)
        except StoreUnavailable as error:
            self._consumers.discard(consumer)
            raise ApiError("unavailable", f"the store does not answer: {error}") from None
        except BaseException:
            self._consumers.discard(consumer)
            raise
        return consumer, [event for event in backlog if stream_filter.matches(event)], gap

    def unsubscribe(self, consumer: Consumer) -> None:
        self._consumers.discard(consumer)

    async def _start_reader(self) -> None:
        if self._reader is not None:
            return
        if self._starting is None:
            self._starting = asyncio.Lock()
        async with self._starting:
            if self._reader is None:
                self._cursor = await self.log.newest()
                self._reader = asyncio.get_running_loop().create_task(self._read())

    async def _read(self) -> None:
        try:
            while self._consumers:
                try:
                    events = await self.log.read(self._cursor, READ_BLOCK_S, READ_COUNT)
                except Exception as error:  # noqa: BLE001 - any failure: log, wait, read again
                    logger.warning(
                        "fix stream read failed", extra={"event": "stream_read_failed", "error": str(error)}
                    )
                    await asyncio.sleep(READ_BLOCK_S)
                    continue
                if events and events[0].id > self._cursor + 1:  # trimmed before this worker read them
                    self._offer(Gap("trimmed", events[0].id - self._cursor - 1, events[0].id))
                for event in events:
                    self._cursor = event.id
                    self._offer(event)
                if events and self.interval_s > 0:
                    # Under load, read (and write to the consumers) at most once an interval, each time all
                    # that came meanwhile: a few large writes instead of one per batch. One write per batch
                    # per consumer raised the vehicles' p99 about tenfold with ten consumers (bench/streams.py),
                    # presumably as each write releases the interpreter lock to the busy filter thread.
                    await asyncio.sleep(self.interval_s)
        finally:
            self._reader = None

    def _offer(self, event: FixEvent | Gap) -> None:
        for consumer in list(self._consumers):
            if not consumer.offer(event):
                self._consumers.discard(consumer)
                lost = consumer.drop() + 1
                self.metrics.stream_events_dropped.labels("slow_consumer").inc(lost)
                logger.info(
                    "slow stream consumer dropped", extra={"event": "stream_consumer_dropped", "lost": lost}
                )

    async def close(self) -> None:
        await self.flush()
        for task in (self._reader, self._publisher):
            if task is not None:
                task.cancel()
        self._consumers.clear()
        await self.log.close()

    # one consumer's events ----------------------------------------------------------------------
    async def events(
        self,
        consumer: Consumer,
        backlog: list[FixEvent],
        gap: Gap | None,
        after: int | None,
        max_rate_hz: float | None,
        still_open: Callable[[], Awaitable[bool]] | None = None,
    ) -> AsyncIterator[bytes]:
        """The consumer's server-sent events: the gap, the backlog, then live fixes and pings."""
        metrics = self.metrics
        metrics.stream_consumers.inc()
        period = None if max_rate_hz is None else 1.0 / max_rate_hz
        last_t: dict[str, float] = {}
        # after an unknown id every held event is sent (their ids are below it); else those after it
        last_id = None if gap is not None and gap.reason == "unknown" else after

        def chunk(items: Sequence[FixEvent | Gap]) -> bytes:
            """The events of ``items`` this consumer gets, as one write (one send per burst, not per fix)."""
            nonlocal last_id
            parts, decimated = [], 0
            for item in items:
                if isinstance(item, Gap):
                    parts.append(missed_event(item, None))
                    continue
                if last_id is not None and item.id <= last_id:
                    continue  # already sent (from the backlog)
                last_id = item.id
                if period is not None:
                    previous = last_t.get(item.vehicle_id)
                    if previous is not None and abs(item.t - previous) < period - _TOLERANCE_S:
                        decimated += 1
                        continue
                    last_t[item.vehicle_id] = item.t
                parts.append(sse("fix", item.data, item.id))
            if decimated:
                metrics.stream_events_dropped.labels("decimated").inc(decimated)
            sent = len(parts) - sum(isinstance(item, Gap) for item in items)
            if sent:
                metrics.stream_events_sent.inc(sent)
            return b"".join(parts)

        try:
            yield b"retry: 1000\n: edgepos fix stream\n\n"
            if gap is not None:
                yield missed_event(gap, after)
            for start in range(0, len(backlog), SEND_CHUNK):
                data = chunk(backlog[start : start + SEND_CHUNK])
                if data:
                    yield data
            while True:
                items = await consumer.take(self.ping_s, SEND_CHUNK)
                if items:
                    data = chunk(items)
                    if data:
                        yield data
                elif consumer.dropped:
                    yield end_event(
                        "slow_consumer",
                        last_id,
                        f"this stream fell {self.queue} fixes behind (EDGEPOS_STREAM_QUEUE) and was dropped so that it "
                        "holds nobody back; reconnect with Last-Event-ID to resume from the stream's buffer",
                    )
                    return
                elif still_open is not None and not await still_open():
                    yield end_event(
                        "session_ended", last_id, "the session whose token opened this stream has ended"
                    )
                    return
                else:
                    yield b": ping\n\n"
        finally:
            self.unsubscribe(consumer)
            metrics.stream_consumers.dec()


def missed_event(gap: Gap, after: int | None) -> bytes:
    if gap.reason == "trimmed":
        message = (
            f"{gap.missed} fixes after the last event id were no longer in the stream's buffer "
            "(EDGEPOS_STREAM_BUFFER) and were missed; the stream goes on with the oldest fixes it holds"
        )
    else:
        message = (
            "the last event id is ahead of this stream (its buffer was reset, e.g. the service restarted with the "
            "in-process store): an unknown number of fixes was missed; the stream goes on with the oldest fixes it holds"
        )
    return sse(
        "missed",
        to_json(
            {
                "reason": gap.reason,
                "last_event_id": None if after is None else str(after),
                "missed": gap.missed,
                "oldest_event_id": None if gap.oldest_id is None else str(gap.oldest_id),
                "message": message,
            }
        ),
    )


def end_event(reason: str, last_id: int | None, message: str) -> bytes:
    data = {"reason": reason, "last_event_id": None if last_id is None else str(last_id), "message": message}
    return sse("end", to_json(data))
