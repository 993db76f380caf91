"""``loadgen/verify.py``: a trip's acknowledged batches judged against the server's counters."""

from __future__ import annotations

import pytest
from edgepos.loadgen.verify import Held, TripLedger, VerifyTally, judge


def ledger(batches: int, epochs_each: int = 5, unanswered: int | None = None) -> TripLedger:
    trip = TripLedger()
    for k in range(batches):
        trip.acknowledge(10.0 + k, epochs_each)
    if unanswered is not None:
        trip.unanswered(unanswered)
    return trip


def test_a_server_holding_every_acknowledged_batch_is_consistent() -> None:
    assert judge(ledger(4), Held(4, 4, 20)) == judge(ledger(4), Held(4, 4, 20))
    verdict = judge(ledger(4), Held(4, 4, 20))
    assert (verdict.found, verdict.lost, verdict.problem) == (4, 0, "")


@pytest.mark.parametrize("applied", [False, True])
def test_a_batch_without_an_answer_may_or_may_not_be_stored(applied: bool) -> None:
    trip = ledger(3, unanswered=5)
    held = Held(4, 4, 20) if applied else Held(3, 3, 15)
    verdict = judge(trip, held)
    assert (verdict.found, verdict.lost, verdict.problem) == (3, 0, "")


def test_holding_more_than_was_sent_is_inconsistent() -> None:
    assert "only 3 batch(es) were sent" in judge(ledger(3), Held(4, 4, 20)).problem
    assert "only 4 batch(es) were sent" in judge(ledger(3, unanswered=5), Held(5, 5, 25)).problem


def test_fewer_batches_held_are_lost_with_the_times_they_were_acknowledged() -> None:
    verdict = judge(ledger(5), Held(2, 2, 10))
    assert (verdict.found, verdict.lost, verdict.problem) == (2, 3, "")
    assert (verdict.lost_from, verdict.lost_until) == (12.0, 14.0)  # batches 3..5, acknowledged at 12, 13, 14


def test_a_gone_session_lost_every_acknowledged_batch() -> None:
    verdict = judge(ledger(3), None)
    assert (verdict.found, verdict.lost, verdict.lost_from, verdict.lost_until) == (0, 3, 10.0, 12.0)
    assert judge(TripLedger(), None) == judge(TripLedger(), Held(0, 0, 0))  # nothing told, nothing lost


def test_counters_that_disagree_with_the_seq_are_named() -> None:
    verdict = judge(ledger(3), Held(3, 3, 14))
    assert verdict.problem == "holds (seq, batches, epochs) (3, 3, 14), expected (3, 3, 15)"
    assert judge(ledger(3), Held(1, 1, 4)).problem  # a loss whose counters disagree too


def test_the_tally_sums_sessions_and_spans_the_loss_window() -> None:
    tally = VerifyTally()
    first, second = ledger(5), ledger(2)
    tally.add("a", first, judge(first, Held(2, 2, 10)), False, 5)  # lost at 12..14
    tally.add("b", second, judge(second, None), True, 5)  # lost at 10..11
    tally.add("c", ledger(4), judge(ledger(4), Held(4, 4, 20)), False, 5)
    tally.add_unreadable("d", ledger(1), "503 unavailable", 5)
    assert (tally.sessions, tally.acknowledged, tally.found, tally.lost) == (4, 12, 6, 5)
    assert (tally.sessions_gone, tally.unreadable, tally.inconsistent) == (1, 1, 0)
    assert tally.loss_window_s() == 4.0 and tally.failed
    assert tally.samples[0] == "a 3 of 5 acknowledged batch(es) lost"
    assert tally.samples[1] == "b 2 of 2 acknowledged batch(es) lost (the session is gone)"
    clean = VerifyTally()
    clean.add("c", ledger(4), judge(ledger(4), Held(4, 4, 20)), False, 5)
    assert not clean.failed and clean.loss_window_s() is None
