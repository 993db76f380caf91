"""Per-key request-rate limiting by the generic cell rate algorithm (GCRA), a token bucket kept as
one number per key: the theoretical arrival time (TAT) of the next request that fits the rate.

A key may send ``burst`` requests at once and then one every ``1 / rate`` seconds. The stores keep
the TAT where every worker sees it (a dict in one process, a SQLite row, a Redis key), so the limit
holds across workers and replicas; the arithmetic is this module's, and the Redis store's Lua script
is a line-by-line transcription of :func:`gcra`.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Waits shorter than this are rounding in the sums of intervals, not a real excess (s).
SLACK_S = 1e-6


@dataclass(frozen=True)
class RateLimit:
    """``rate_per_s`` sustained requests per second with bursts of up to ``burst`` requests."""

    rate_per_s: float
    burst: int

    def __post_init__(self) -> None:
        if not self.rate_per_s > 0:
            raise ValueError("rate_per_s must be > 0")
        if self.burst < 1:
            raise ValueError("burst must be >= 1")

    @property
    def interval_s(self) -> float:
        """Seconds of budget one request uses."""
        return 1.0 / self.rate_per_s

    @property
    def tolerance_s(self) -> float:
        """How far ahead of now the TAT may run before requests are refused."""
        return (self.burst - 1) * self.interval_s


def gcra(tat: float | None, now: float, limit: RateLimit) -> tuple[float, float | None]:
    """One request at ``now`` against the stored ``tat`` (None: never seen or expired).

    Returns ``(wait_s, new_tat)``: ``wait_s == 0`` and the TAT to store when the request is allowed;
    otherwise the seconds until it would be allowed and None (a refused request uses no budget).
    """
    start = now if tat is None or tat < now else tat
    wait = start - now - limit.tolerance_s
    if wait > SLACK_S:
        return wait, None
    return 0.0, start + limit.interval_s


def keep_for_s(new_tat: float, now: float) -> float:
    """How long a stored TAT matters: once it is in the past the key has its whole burst again."""
    return max(0.0, new_tat - now)
