"""Benchmark: the CPU a job costs to pass through the fair scheduler, beside a plain thread hop.

N vehicles (asyncio tasks) each await M jobs in turn, all at once, on one event loop, through
(1) ``FairScheduler.run`` (light lane), (2) ``loop.run_in_executor`` on a one-thread executor (what the
service did before the scheduler: no turns), and (3) the same job called inline (the job's own cost).
Prints the process CPU per job of each, per round, and the medians; ``scheduler - inline`` is what a
light batch pays to leave the event loop. CPU time, not wall time: the machine is shared.

    python bench/scheduler_overhead.py --vehicles 16 --jobs 1500 --rounds 5
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor

from edgepos.api.metrics import Metrics
from edgepos.api.scheduler import FairScheduler


def _job(iterations: int) -> int:
    """A stand-in for a light batch's filter step: pure Python work of a fixed size."""
    total = 0
    for value in range(iterations):
        total += value
    return total


async def _round(vehicles: int, jobs: int, iterations: int) -> dict[str, float]:
    scheduler = FairScheduler(Metrics(), heavy_workers=0)
    executor = ThreadPoolExecutor(1, thread_name_prefix="plain")
    loop = asyncio.get_running_loop()

    async def through_scheduler(vehicle: int) -> None:
        for _ in range(jobs):
            await scheduler.run(f"vehicle-{vehicle}", 0.0, "bench", _job, iterations)

    async def through_executor(_vehicle: int) -> None:
        for _ in range(jobs):
            await loop.run_in_executor(executor, _job, iterations)

    figures: dict[str, float] = {}
    for name, one in (("scheduler", through_scheduler), ("plain executor", through_executor)):
        started = time.process_time()
        await asyncio.gather(*(one(vehicle) for vehicle in range(vehicles)))
        figures[name] = (time.process_time() - started) / (vehicles * jobs) * 1e6
    started = time.process_time()
    for _ in range(vehicles * jobs):
        _job(iterations)
    figures["inline"] = (time.process_time() - started) / (vehicles * jobs) * 1e6
    scheduler.shutdown()
    executor.shutdown()
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=16)
    parser.add_argument("--jobs", type=int, default=1500, help="jobs per vehicle per round")
    parser.add_argument("--iterations", type=int, default=3000, help="size of a job (about 100 us)")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    print(
        f"process CPU per job (us), {args.vehicles} vehicles x {args.jobs} jobs per round; "
        f"load average {os.getloadavg()[0]:.2f}"
    )
    rows: list[dict[str, float]] = []
    for index in range(args.rounds):
        figures = asyncio.run(_round(args.vehicles, args.jobs, args.iterations))
        rows.append(figures)
        print(f"round {index + 1}  " + "  ".join(f"{name} {value:6.1f}" for name, value in figures.items()))
    medians = {name: statistics.median(row[name] for row in rows) for name in rows[0]}
    print("medians  " + "  ".join(f"{name} {value:6.1f}" for name, value in medians.items()))
    print(
        f"off the loop, per job: scheduler {medians['scheduler'] - medians['inline']:.1f} us, "
        f"plain executor {medians['plain executor'] - medians['inline']:.1f} us"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
