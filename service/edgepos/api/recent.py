"""The service's figures over the last few seconds (epochs/s, batches/s, batch latency p99) for the
operator map's header (GET /v1/status).

Prometheus keeps counters and bucketed histograms, from which a rate or a quantile needs two scrapes and
a bucket interpolation; the map wants exact figures at a glance from one request, so each worker also keeps
the events of the last ``window_s`` seconds here. Bounded: older events are dropped as new ones come, and
at most ``max_events`` of each kind are kept (the oldest go first), so a burst cannot grow memory without
limit.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

WINDOW_S = 10.0
MAX_EVENTS = 100_000
"""Per kind: 10 000 batches/s over the 10 s window, far above one worker's rate; about 10 MB at most."""
_T = TypeVar("_T", int, float)


@dataclass(frozen=True)
class RecentFigures:
    """What one worker did during the window ending now."""

    window_s: float
    epochs_per_s: float
    batches_per_s: float
    batch_latency_p99_s: float | None
    """None when no batch request was answered in the window."""
    batch_requests: int
    """Batch requests answered in the window (any status): what the p99 is of."""


def quantile(values: list[float], q: float) -> float:
    """The q-quantile by the nearest-rank method (the smallest value with at least q of the values at or
    below it): an observed latency, never an interpolation between two."""
    if not values:
        raise ValueError("quantile of no values")
    ordered = sorted(values)
    rank = max(1, math.ceil(q * len(ordered)))
    return ordered[rank - 1]


class RecentWindow:
    """Applied batches (time, epochs) and answered batch requests (time, seconds) of the last window."""

    def __init__(
        self,
        window_s: float = WINDOW_S,
        max_events: int = MAX_EVENTS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if window_s <= 0:
            raise ValueError("window_s must be > 0")
        self.window_s = window_s
        self._clock = clock
        self._epochs: deque[tuple[float, int]] = deque(maxlen=max_events)
        self._latencies: deque[tuple[float, float]] = deque(maxlen=max_events)

    def add_batch(self, epochs: int) -> None:
        now = self._clock()
        self._epochs.append((now, epochs))
        self._trim(self._epochs, now)

    def add_latency(self, seconds: float) -> None:
        now = self._clock()
        self._latencies.append((now, seconds))
        self._trim(self._latencies, now)

    def _trim(self, events: deque[tuple[float, _T]], now: float) -> None:
        """Forget the events older than the window (on every write too: memory follows the rate, whether
        or not anyone reads the figures)."""
        oldest = now - self.window_s
        while events and events[0][0] < oldest:
            events.popleft()

    def figures(self) -> RecentFigures:
        now = self._clock()
        self._trim(self._epochs, now)
        self._trim(self._latencies, now)
        latencies = [seconds for _, seconds in self._latencies]
        return RecentFigures(
            window_s=self.window_s,
            epochs_per_s=sum(epochs for _, epochs in self._epochs) / self.window_s,
            batches_per_s=len(self._epochs) / self.window_s,
            batch_latency_p99_s=quantile(latencies, 0.99) if latencies else None,
            batch_requests=len(latencies),
        )
