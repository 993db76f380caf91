"""Parallel Monte Carlo over runs: fixed chunks of run indices, one worker pool, an ordered reduction.

Chunk boundaries depend only on the number of runs and partial results are combined in chunk order,
so the totals are bit-for-bit the same whatever the number of worker processes.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from edgepos.eval.progress import Progress

T = TypeVar("T")

#: Aim for about this many chunks: enough to balance two cores and to move the progress line.
_TARGET_CHUNKS = 100


def chunk_runs(runs: int) -> list[range]:
    """Run indices 0..runs-1 in consecutive chunks whose size depends on ``runs`` only."""
    if runs < 1:
        raise ValueError("runs must be at least 1")
    size = max(1, runs // _TARGET_CHUNKS)
    return [range(start, min(start + size, runs)) for start in range(0, runs, size)]


def run_chunks(
    work: Callable[[range], T],
    combine: Callable[[T, T], T],
    chunks: Sequence[range],
    workers: int,
    initializer: Callable[..., None],
    initargs: tuple[Any, ...] = (),
    progress: Progress | None = None,
) -> T:
    """``work`` every chunk (in a pool of ``workers`` processes when more than one) and fold the
    results with ``combine`` in chunk order. ``initializer(*initargs)`` prepares each process.

    ``work`` and ``initializer`` must be module-level functions so the pool can pickle them.
    """
    if not chunks:
        raise ValueError("no chunks to run")
    total: T | None = None

    def fold(chunk: range, result: T) -> None:
        nonlocal total
        total = result if total is None else combine(total, result)
        if progress is not None:
            progress.advance(len(chunk))

    processes = min(workers, len(chunks))
    if processes <= 1:
        initializer(*initargs)
        for chunk in chunks:
            fold(chunk, work(chunk))
    else:
        with multiprocessing.Pool(processes, initializer, initargs) as pool:
            for chunk, result in zip(chunks, pool.imap(work, chunks)):
                fold(chunk, result)
    assert total is not None
    return total
