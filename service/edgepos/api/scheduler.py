"""Fair scheduling of estimation work: no vehicle's batches can stall another's.

Estimation never runs on the event loop. Each job carries the vehicle it is for and its predicted CPU
cost (``pipelines.cost``), and goes to one of two lanes:

- the **light lane**, one thread of this process, takes jobs predicted to fit a slice
  (EDGEPOS_SCHEDULER_SLICE_MS): almost every batch, at no more cost than a thread hop;
- the **heavy lane**, a pool of worker processes (EDGEPOS_HEAVY_WORKERS), takes the rest, so that a
  batch of thousands of particles runs where it cannot hold this process's interpreter lock against
  the light lane. With no heavy workers the heavy lane is a second thread (the lock is then shared).

Each lane serves the vehicles with waiting jobs in turn (round robin), one job per turn, so a vehicle
that queues many jobs waits for its own, not others for it; how many jobs one vehicle may have
waiting or running is bounded (EDGEPOS_MAX_QUEUED_PER_VEHICLE) and beyond it the answer is 429 with
Retry-After. Why processes and not sub-interpreters: on CPython 3.11, which this service runs on,
sub-interpreters share one interpreter lock (a lock per interpreter came with 3.12), so they could not
keep a heavy batch from holding the light lane's lock; processes can.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import logging
import multiprocessing
import os
import threading
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

from edgepos.api.errors import ApiError
from edgepos.api.metrics import Metrics

logger = logging.getLogger("edgepos.api")

Result = TypeVar("Result")
LaneName = Literal["light", "heavy"]


def _timed(function: Callable[..., Result], *args: Any) -> tuple[Result, float]:
    """Run ``function`` and return its result with the CPU seconds this thread spent on it (runs in
    the lane's thread or worker process, so the figure is the job's own)."""
    started = time.thread_time()
    result = function(*args)
    return result, time.thread_time() - started


ORPHAN_CHECK_S = 1.0
"""How often a heavy-lane worker checks that the process that started it is still there."""


def _exit_when_orphaned(parent: int) -> None:
    """A heavy-lane worker whose service process died (SIGKILL, a crash: no shutdown told it) exits
    instead of lingering with its few hundred MB."""
    while True:
        time.sleep(ORPHAN_CHECK_S)
        if os.getppid() != parent:
            os._exit(0)


def _warm_worker(parent: int) -> None:
    """Heavy-lane worker start-up: watch the parent, and compile (or load from numba's cache) the filter
    kernels now, not in the first heavy batch."""
    threading.Thread(
        target=_exit_when_orphaned, args=(parent,), daemon=True, name="edgepos-orphan-watch"
    ).start()
    from edgepos.core.compiled import warm_up

    warm_up()


@dataclass
class _Job:
    key: str
    label: str
    call: functools.partial[tuple[Any, float]]
    future: asyncio.Future[Any]
    queued_at: float
    executor: Executor | None = None


@dataclass
class _Lane:
    """Jobs waiting per vehicle, the order vehicles are served in, and the executor that runs them."""

    name: LaneName
    capacity: int
    make_executor: Callable[[], Executor]
    executor: Executor | None = None
    waiting: dict[str, collections.deque[_Job]] = field(default_factory=dict)
    turns: collections.OrderedDict[str, None] = field(default_factory=collections.OrderedDict)
    running: int = 0

    def depth(self) -> int:
        return sum(len(jobs) for jobs in self.waiting.values())

    def get_executor(self) -> Executor:
        if self.executor is None:
            self.executor = self.make_executor()
        return self.executor


class FairScheduler:
    """Runs estimation jobs off the event loop, vehicles served in turn, heavy jobs in processes."""

    def __init__(
        self,
        metrics: Metrics,
        *,
        slice_s: float = 0.010,
        heavy_workers: int = 1,
        max_queued_per_key: int = 4,
    ) -> None:
        self.metrics = metrics
        self.slice_s = slice_s
        self.heavy_workers = heavy_workers
        self.max_queued_per_key = max_queued_per_key
        self._per_key: collections.Counter[str] = collections.Counter()
        light = _Lane("light", 1, lambda: ThreadPoolExecutor(1, thread_name_prefix="edgepos-filter"))
        if heavy_workers > 0:
            heavy = _Lane("heavy", heavy_workers, self._process_pool)
        else:
            heavy = _Lane("heavy", 1, lambda: ThreadPoolExecutor(1, thread_name_prefix="edgepos-heavy"))
        self._lanes: dict[LaneName, _Lane] = {"light": light, "heavy": heavy}

    def _process_pool(self) -> Executor:
        # spawn, not fork: the parent runs threads (the light lane, the store's), which fork would copy
        # in whatever state they were in.
        context = multiprocessing.get_context("spawn")
        return ProcessPoolExecutor(
            self.heavy_workers, mp_context=context, initializer=_warm_worker, initargs=(os.getpid(),)
        )

    def lane_for(self, cost_s: float) -> LaneName:
        return "light" if cost_s <= self.slice_s else "heavy"

    @contextlib.asynccontextmanager
    async def hold(self, key: str) -> AsyncIterator[None]:
        """A place in ``key``'s line (a vehicle's or a session's requests that want the filter), for
        the time of the request; 429 (ApiError) when ``key`` already holds ``max_queued_per_key`` places.
        Held around the whole request, so a vehicle that pipelines requests cannot occupy the worker's
        admission slots waiting on its own session."""
        if self._per_key[key] >= self.max_queued_per_key:
            self.metrics.rate_limited.labels("vehicle_queue").inc()
            raise ApiError(
                "rate_limited",
                f"this vehicle already has {self.max_queued_per_key} requests waiting or being filtered "
                "(EDGEPOS_MAX_QUEUED_PER_VEHICLE); send the next when one is answered",
                headers={"Retry-After": "1"},
            )
        self._per_key[key] += 1
        try:
            yield
        finally:
            self._per_key[key] -= 1
            if self._per_key[key] <= 0:
                del self._per_key[key]

    async def run(
        self, key: str, cost_s: float, label: str, function: Callable[..., Result], *args: Any
    ) -> Result:
        """Run ``function(*args)`` for vehicle ``key`` in its turn, on the lane its predicted CPU cost
        ``cost_s`` chooses; ``label`` names the work in the metrics (the pipeline)."""
        lane = self._lanes[self.lane_for(cost_s)]
        loop = asyncio.get_running_loop()
        job = _Job(key, label, functools.partial(_timed, function, *args), loop.create_future(), loop.time())
        lane.waiting.setdefault(key, collections.deque()).append(job)
        lane.turns.setdefault(key, None)
        self.metrics.queue_depth.labels(lane.name).set(lane.depth())
        self._dispatch(lane)
        result: Result = await job.future
        return result

    def _dispatch(self, lane: _Lane) -> None:
        """Start the next vehicles' jobs while the lane has room: the vehicle whose turn it is first."""
        loop = asyncio.get_running_loop()
        while lane.running < lane.capacity and lane.turns:
            key, _ = lane.turns.popitem(last=False)
            jobs = lane.waiting[key]
            job = jobs.popleft()
            if jobs:
                lane.turns[key] = None  # its next job waits for everyone else's turn
            else:
                del lane.waiting[key]
            if job.future.cancelled():  # the request went away while it waited
                continue
            lane.running += 1
            self.metrics.queue_depth.labels(lane.name).set(lane.depth())
            self.metrics.queue_wait.labels(lane.name).observe(loop.time() - job.queued_at)
            job.executor = lane.get_executor()
            try:
                running = loop.run_in_executor(job.executor, job.call)
            except BrokenProcessPool:  # a worker died since the last job: start a fresh pool
                self._retire(lane, job.executor)
                job.executor = lane.get_executor()
                running = loop.run_in_executor(job.executor, job.call)
            running.add_done_callback(functools.partial(self._finished, lane, job))

    def _retire(self, lane: _Lane, broken: Executor | None) -> None:
        """A heavy worker died (killed, out of memory): drop its pool, once, so the next job starts
        a fresh one (other jobs of the same pool fail alike and must not retire its successor)."""
        if broken is not None and lane.executor is broken:
            logger.error("heavy-lane worker pool broken; a new one starts", extra={"event": "pool_broken"})
            lane.executor = None
            broken.shutdown(wait=False, cancel_futures=True)

    def _finished(self, lane: _Lane, job: _Job, running: asyncio.Future[Any]) -> None:
        lane.running -= 1
        if not job.future.cancelled():
            error = running.exception()
            if error is None:
                result, cpu_s = running.result()
                self.metrics.pipeline_cpu.labels(job.label).inc(cpu_s)
                job.future.set_result(result)
            elif isinstance(error, BrokenProcessPool):
                self._retire(lane, job.executor)
                job.future.set_exception(
                    ApiError("unavailable", "the worker filtering this batch stopped; retry the same batch")
                )
            else:
                job.future.set_exception(error)
        self._dispatch(lane)

    def held(self, key: str) -> int:
        """Places ``key`` holds in its line."""
        return self._per_key.get(key, 0)

    def shutdown(self) -> None:
        """Stop the lanes once their current work is done (app shutdown). Worker processes are waited
        for (a heavy batch is bounded by the CPU budget), so none outlives the service."""
        for lane in self._lanes.values():
            if lane.executor is not None:
                lane.executor.shutdown(
                    wait=isinstance(lane.executor, ProcessPoolExecutor), cancel_futures=True
                )
                lane.executor = None
