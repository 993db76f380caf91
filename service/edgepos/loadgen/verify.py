"""``edgepos loadtest --verify``: what each vehicle was acknowledged against what the server holds.

Every session is read back, also one that saw an error: the sessions a fault touched are the ones
worth checking. A vehicle sends its batches in seq order and abandons the trip at the first error, so
the server must hold exactly the acknowledged batches 1..A, or A + 1 when the last batch got no
answer (a timeout or a 5xx: it may have been applied before the failure). Holding fewer means
acknowledged batches were lost: they are counted, with the time each was acknowledged, so the
report can say over which window of the run acknowledged writes were lost (a Redis that died
before its append-only file reached the disk, a failover to a replica that had not caught up).
Holding more than was sent, or counters that disagree with the seq, is an inconsistency.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class TripLedger:
    """What one trip's vehicle was told: when each batch was acknowledged and the session's epoch count
    after it, and the epochs of a batch that got no answer (its outcome is unknown)."""

    acknowledged_at: list[float] = field(default_factory=list)
    epochs_after: list[int] = field(default_factory=list)
    unanswered_epochs: int | None = None

    @property
    def acknowledged(self) -> int:
        return len(self.acknowledged_at)

    @property
    def epochs(self) -> int:
        return self.epochs_after[-1] if self.epochs_after else 0

    def acknowledge(self, at: float, epochs: int) -> None:
        self.acknowledged_at.append(at)
        self.epochs_after.append(self.epochs + epochs)

    def unanswered(self, epochs: int) -> None:
        """The next batch was sent and no answer came back: the server may or may not hold it."""
        self.unanswered_epochs = epochs


@dataclass(frozen=True)
class Held:
    """A session's counters as the server reports them."""

    last_seq: int
    batches: int
    epochs: int


@dataclass(frozen=True)
class Verdict:
    """One session judged: acknowledged batches found and lost, when the lost ones were acknowledged,
    and what else disagrees ("" when nothing)."""

    found: int
    lost: int
    lost_from: float | None = None
    lost_until: float | None = None
    problem: str = ""


def judge(ledger: TripLedger, held: Held | None) -> Verdict:
    """Compare a trip's ledger with the server's counters (``held`` None: the session is gone)."""
    told = ledger.acknowledged
    times = ledger.acknowledged_at
    if held is None:
        if told == 0:
            return Verdict(0, 0)
        return Verdict(0, told, times[0], times[-1])
    seq = held.last_seq
    if seq < 0:
        return Verdict(0, 0, problem=f"holds a negative seq {seq}")
    if seq < told:
        expected_epochs = ledger.epochs_after[seq - 1] if seq else 0
        problem = _counters_problem(held, seq, expected_epochs)
        return Verdict(seq, told - seq, times[seq], times[-1], problem)
    if seq == told:
        return Verdict(told, 0, problem=_counters_problem(held, seq, ledger.epochs))
    if seq == told + 1 and ledger.unanswered_epochs is not None:
        # the batch that got no answer was applied before the failure: consistent
        expected_epochs = ledger.epochs + ledger.unanswered_epochs
        return Verdict(told, 0, problem=_counters_problem(held, seq, expected_epochs))
    sent = told + (ledger.unanswered_epochs is not None)
    return Verdict(told, 0, problem=f"holds seq {seq}, but only {sent} batch(es) were sent")


def _counters_problem(held: Held, seq: int, epochs: int) -> str:
    if (held.batches, held.epochs) == (seq, epochs):
        return ""
    return f"holds (seq, batches, epochs) ({seq}, {held.batches}, {held.epochs}), expected ({seq}, {seq}, {epochs})"


@dataclass
class VerifyTally:
    """Every session's verdict summed up for the report."""

    sessions: int = 0
    acknowledged: int = 0
    found: int = 0
    lost: int = 0
    sessions_gone: int = 0
    unreadable: int = 0
    inconsistent: int = 0
    lost_from: float | None = None
    lost_until: float | None = None
    samples: list[str] = field(default_factory=list)

    def add(self, name: str, ledger: TripLedger, verdict: Verdict, gone: bool, max_samples: int) -> None:
        self.sessions += 1
        self.acknowledged += ledger.acknowledged
        self.found += verdict.found
        self.lost += verdict.lost
        self.sessions_gone += gone
        if verdict.lost_from is not None and verdict.lost_until is not None:
            self.lost_from = (
                verdict.lost_from if self.lost_from is None else min(self.lost_from, verdict.lost_from)
            )
            self.lost_until = (
                verdict.lost_until if self.lost_until is None else max(self.lost_until, verdict.lost_until)
            )
        if verdict.problem:
            self.inconsistent += 1
        note = verdict.problem or (
            f"{verdict.lost} of {ledger.acknowledged} acknowledged batch(es) lost"
            + (" (the session is gone)" if gone else "")
            if verdict.lost
            else ""
        )
        if note and len(self.samples) < max_samples:
            self.samples.append(f"{name} {note}")

    def add_unreadable(self, name: str, ledger: TripLedger, why: str, max_samples: int) -> None:
        self.sessions += 1
        self.acknowledged += ledger.acknowledged
        self.unreadable += 1
        if len(self.samples) < max_samples:
            self.samples.append(f"{name} could not be read back: {why}")

    @property
    def failed(self) -> bool:
        """Whether the check failed: anything lost, inconsistent or left unread."""
        return bool(self.lost or self.inconsistent or self.unreadable)

    def loss_window_s(self) -> float | None:
        """Seconds from the acknowledgement of the earliest lost batch to that of the latest (None: none lost)."""
        if self.lost_from is None or self.lost_until is None:
            return None
        return self.lost_until - self.lost_from
