"""Fair scheduling of estimation work: no vehicle's batches can stall another's.

Each job carries the vehicle it is for and its predicted CPU cost (``pipelines.cost``), and goes to one
of two lanes:

- the **light lane** takes jobs predicted to fit a slice (EDGEPOS_SCHEDULER_SLICE_MS): almost every
  batch. By default (EDGEPOS_LIGHT_LANE=thread) it runs them on one filter thread of this process; with
  ``loop`` on the event loop's own thread, one job per turn, the loop serving its sockets between two
  jobs;
- the **heavy lane**, a pool of worker processes (EDGEPOS_HEAVY_WORKERS), takes the rest, so that a
  batch of thousands of particles runs where it cannot hold this process's interpreter lock against
  the light lane. With no heavy workers the heavy lane is a second thread (the lock is then shared).

Each lane serves the vehicles with waiting jobs in turn (round robin), one job per turn, so a vehicle
that queues many jobs waits for its own, not others for it; how many jobs one vehicle may have
waiting or running is bounded (EDGEPOS_MAX_QUEUED_PER_VEHICLE) and beyond it the answer is 429 with
Retry-After. Why processes and not sub-interpreters: on CPython 3.11, which this service runs on,
sub-interpreters share one interpreter lock (a lock per interpreter came with 3.12), so they could not
keep a heavy batch from holding the light lane's lock; processes can.

Why the light lane runs on a thread by default: a batch's run of epochs is one compiled call that releases
the interpreter lock (``core.kernels_base._jit_nogil``), some 400 us for 20 epochs, during which the event
loop reads, validates and answers other requests on the other core. Before the run was one call, the
kernels ran three times an epoch holding the lock, and the thread only took turns with the loop: one
worker then spent 24-53 % more CPU per epoch and served 19-33 % fewer epochs with the thread, so the loop
was the default. Now, one worker under wrk serves 1.06-1.36 times the epochs/s on the thread, two workers
about the same with a shorter p99 (docs/benchmarks.md). ``loop`` stays for deployments that would rather
not have the thread. The site's own work (kernel warm-up, parsing uploaded files) has no predicted cost
and always runs on a thread, never on the loop.
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
from concurrent.futures import Executor, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

from prometheus_client import Counter

from edgepos.api.errors import ApiError
from edgepos.api.metrics import Metrics

logger = logging.getLogger("edgepos.api")

Result = TypeVar("Result")
LaneName = Literal["light", "heavy", "site"]
LightLane = Literal["loop", "thread"]


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


class _PipelineCpu:
    """The pipeline CPU counter's child of each label, looked up once: ``labels()`` takes the metric's
    lock and checks its values on every call, once per batch in every lane."""

    def __init__(self, metrics: Metrics) -> None:
        self._counter = metrics.pipeline_cpu
        self._children: dict[str, Counter] = {}

    def add(self, label: str, cpu_s: float) -> None:
        child = self._children.get(label)
        if child is None:  # two threads may both look it up: labels() gives both the same child
            child = self._children[label] = self._counter.labels(label)
        child.inc(cpu_s)


@dataclass
class _Job:
    key: str
    label: str
    call: functools.partial[tuple[Any, float]]
    future: asyncio.Future[Any]
    loop: asyncio.AbstractEventLoop
    queued_at: float
    executor: Executor | None = None


@dataclass
class _RoundRobin:
    """Jobs waiting per key and the order keys are served in: one job per turn, and a key with more
    jobs goes to the back of the line after each."""

    waiting: dict[str, collections.deque[_Job]] = field(default_factory=dict)
    turns: collections.OrderedDict[str, None] = field(default_factory=collections.OrderedDict)
    count: int = 0  # jobs waiting, kept as they come and go: read twice per job, summed it cost O(keys)

    def push(self, job: _Job) -> None:
        self.waiting.setdefault(job.key, collections.deque()).append(job)
        self.turns.setdefault(job.key, None)
        self.count += 1

    def pop(self) -> _Job | None:
        """The next job in turn, or None when nothing waits."""
        if not self.turns:
            return None
        key, _ = self.turns.popitem(last=False)
        jobs = self.waiting[key]
        job = jobs.popleft()
        if jobs:
            self.turns[key] = None  # its next job waits for everyone else's turn
        else:
            del self.waiting[key]
        self.count -= 1
        return job

    def depth(self) -> int:
        return self.count

    def drain(self) -> list[_Job]:
        jobs = [job for line in self.waiting.values() for job in line]
        self.waiting.clear()
        self.turns.clear()
        self.count = 0
        return jobs


def _settle(job: _Job, result: Any, error: BaseException | None) -> None:
    """Hand a job's outcome to the request awaiting it (on the event loop's thread)."""
    if job.future.cancelled():
        return
    if error is None:
        job.future.set_result(result)
    else:
        job.future.set_exception(error)


class _ThreadLane:
    """One thread that takes the next job in turn itself, as soon as the last one ends.

    Why not a ThreadPoolExecutor fed from the event loop: fed one job at a time (to keep the turns), the
    thread sleeps after every job until the loop hands it the next, two thread wake-ups per job that cost
    more CPU than a light batch's filter step (bench/scheduler_overhead.py); fed several, the executor's
    queue would be first come, first served. Here the thread picks in turn under a lock, and only sleeps
    when nothing waits; the loop is told of each result with ``call_soon_threadsafe``."""

    def __init__(self, name: LaneName, metrics: Metrics, thread_name: str) -> None:
        self.name = name
        self.metrics = metrics
        self.thread_name = thread_name
        self._line = _RoundRobin()
        self._ready = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stopping = False
        self._depth = metrics.queue_depth.labels(name)  # labelled once: labels() takes a lock each call
        self._wait = metrics.queue_wait.labels(name)
        self._cpu = _PipelineCpu(metrics)

    def submit(self, job: _Job) -> None:
        with self._ready:
            self._line.push(job)
            depth = self._line.depth()
            if self._thread is None:
                self._thread = threading.Thread(target=self._serve, name=self.thread_name, daemon=True)
                self._thread.start()
            self._ready.notify()
        self._depth.set(depth)

    def _serve(self) -> None:
        while True:
            with self._ready:
                job = self._line.pop()
                while job is None and not self._stopping:
                    self._ready.wait()
                    job = self._line.pop()
                if job is None:
                    return
                depth = self._line.depth()
            if job.future.cancelled():  # the request went away while it waited
                continue
            self._depth.set(depth)
            self._wait.observe(time.monotonic() - job.queued_at)
            try:
                result, cpu_s = job.call()
            except BaseException as error:  # noqa: BLE001  # every error goes back to the request that waits for it
                outcome: tuple[Any, BaseException | None] = (None, error)
            else:
                self._cpu.add(job.label, cpu_s)
                outcome = (result, None)
            try:
                job.loop.call_soon_threadsafe(_settle, job, *outcome)
            except RuntimeError:  # the loop closed meanwhile (shutdown): nobody waits for the result
                pass

    def shutdown(self) -> None:
        """Let the thread end after its current job; jobs still waiting are cancelled."""
        with self._ready:
            self._stopping = True
            waiting = self._line.drain()
            self._ready.notify_all()
        for job in waiting:
            try:
                job.loop.call_soon_threadsafe(job.future.cancel)
            except RuntimeError:  # the loop closed already: nobody waits for the job
                pass


class _LoopLane:
    """The event loop's own thread, vehicles in turn: one task takes the next job in turn, runs it and
    yields to the loop (its sockets, the requests that queue meanwhile) before the next. Every job goes
    through the line, even on an idle lane, so jobs that become ready together are served in turn."""

    def __init__(self, name: LaneName, metrics: Metrics) -> None:
        self.name = name
        self.metrics = metrics
        self._line = _RoundRobin()
        self._serving: asyncio.Task[None] | None = None
        self._depth = metrics.queue_depth.labels(name)
        self._wait = metrics.queue_wait.labels(name)
        self._cpu = _PipelineCpu(metrics)

    def submit(self, job: _Job) -> None:
        self._line.push(job)
        self._depth.set(self._line.depth())
        if self._serving is None or self._serving.get_loop() is not job.loop:  # none, or of a closed loop
            self._serving = job.loop.create_task(self._serve())

    async def _serve(self) -> None:
        try:
            while (job := self._line.pop()) is not None:
                self._depth.set(self._line.depth())
                if job.future.cancelled():  # the request went away while it waited
                    continue
                self._wait.observe(time.monotonic() - job.queued_at)
                try:
                    result, cpu_s = job.call()
                except Exception as error:  # noqa: BLE001  # every error goes back to the request that waits for it
                    job.future.set_exception(error)
                except BaseException:
                    job.future.cancel()  # KeyboardInterrupt, SystemExit: free the request, then stop the loop
                    raise
                else:
                    self._cpu.add(job.label, cpu_s)
                    job.future.set_result(result)
                await asyncio.sleep(0)  # the loop's sockets and callbacks before the next job
        finally:
            self._serving = None

    def shutdown(self) -> None:
        """Jobs still waiting are cancelled; the job running, if any, ends first (it holds the loop)."""
        for job in self._line.drain():
            job.future.cancel()
        if self._serving is not None:
            self._serving.cancel()


class _PoolLane:
    """Worker processes fed from the event loop, at most one job per worker at a time, vehicles in turn."""

    def __init__(
        self, name: LaneName, metrics: Metrics, capacity: int, make_executor: Callable[[], Executor]
    ):
        self.name = name
        self.metrics = metrics
        self.capacity = capacity
        self.make_executor = make_executor
        self.executor: Executor | None = None
        self._line = _RoundRobin()
        self.running = 0
        self._cpu = _PipelineCpu(metrics)

    def get_executor(self) -> Executor:
        if self.executor is None:
            self.executor = self.make_executor()
        return self.executor

    def submit(self, job: _Job) -> None:
        self._line.push(job)
        self.metrics.queue_depth.labels(self.name).set(self._line.depth())
        self._dispatch()

    def _dispatch(self) -> None:
        """Start the next vehicles' jobs while the lane has room: the vehicle whose turn it is first."""
        while self.running < self.capacity:
            job = self._line.pop()
            if job is None:
                return
            if job.future.cancelled():  # the request went away while it waited
                continue
            self.running += 1
            self.metrics.queue_depth.labels(self.name).set(self._line.depth())
            self.metrics.queue_wait.labels(self.name).observe(time.monotonic() - job.queued_at)
            job.executor = self.get_executor()
            try:
                running = job.loop.run_in_executor(job.executor, job.call)
            except BrokenProcessPool:  # a worker died since the last job: start a fresh pool
                self._retire(job.executor)
                job.executor = self.get_executor()
                running = job.loop.run_in_executor(job.executor, job.call)
            running.add_done_callback(functools.partial(self._finished, job))

    def _retire(self, broken: Executor | None) -> None:
        """A worker died (killed, out of memory): drop its pool, once, so the next job starts a fresh one
        (other jobs of the same pool fail alike and must not retire its successor)."""
        if broken is not None and self.executor is broken:
            logger.error("heavy-lane worker pool broken; a new one starts", extra={"event": "pool_broken"})
            self.executor = None
            broken.shutdown(wait=False, cancel_futures=True)

    def _finished(self, job: _Job, running: asyncio.Future[Any]) -> None:
        self.running -= 1
        if not job.future.cancelled():
            error = running.exception()
            if error is None:
                result, cpu_s = running.result()
                self._cpu.add(job.label, cpu_s)
                job.future.set_result(result)
            elif isinstance(error, BrokenProcessPool):
                self._retire(job.executor)
                job.future.set_exception(
                    ApiError("unavailable", "the worker filtering this batch stopped; retry the same batch")
                )
            else:
                job.future.set_exception(error)
        self._dispatch()

    def shutdown(self) -> None:
        """Worker processes are waited for (a heavy batch is bounded by the CPU budget), so none outlives
        the service; jobs still waiting are cancelled."""
        for job in self._line.drain():
            job.future.cancel()
        if self.executor is not None:
            self.executor.shutdown(wait=True, cancel_futures=True)
            self.executor = None


class FairScheduler:
    """Runs estimation jobs off the event loop, vehicles served in turn, heavy jobs in processes."""

    def __init__(
        self,
        metrics: Metrics,
        *,
        slice_s: float = 0.010,
        heavy_workers: int = 1,
        max_queued_per_key: int = 4,
        light_lane: LightLane = "thread",
    ) -> None:
        self.metrics = metrics
        self.slice_s = slice_s
        self.heavy_workers = heavy_workers
        self.max_queued_per_key = max_queued_per_key
        self._per_key: collections.Counter[str] = collections.Counter()
        light: _LoopLane | _ThreadLane = (
            _LoopLane("light", metrics)
            if light_lane == "loop"
            else _ThreadLane("light", metrics, "edgepos-filter")
        )
        self._lanes: dict[LaneName, _LoopLane | _ThreadLane | _PoolLane] = {
            "light": light,
            "heavy": (
                _PoolLane("heavy", metrics, heavy_workers, self._process_pool)
                if heavy_workers > 0
                else _ThreadLane("heavy", metrics, "edgepos-heavy")
            ),
            # the site's own work, of no predicted cost, never on the loop: the light lane's thread if it
            # has one, else a thread of its own (started with the first such job)
            "site": light if isinstance(light, _ThreadLane) else _ThreadLane("site", metrics, "edgepos-site"),
        }

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
        return await self._run_on(self.lane_for(cost_s), key, label, function, *args)

    async def run_site(self, function: Callable[..., Result], *args: Any) -> Result:
        """Run the site's own CPU work (kernel warm-up, parsing an uploaded file: no predicted cost) on a
        thread, never on the event loop; with a thread light lane, in turn with the vehicles' batches."""
        return await self._run_on("site", "site", "site", function, *args)

    async def _run_on(
        self, lane: LaneName, key: str, label: str, function: Callable[..., Result], *args: Any
    ) -> Result:
        loop = asyncio.get_running_loop()
        call = functools.partial(_timed, function, *args)
        job = _Job(key, label, call, loop.create_future(), loop, time.monotonic())
        self._lanes[lane].submit(job)
        result: Result = await job.future
        return result

    def held(self, key: str) -> int:
        """Places ``key`` holds in its line."""
        return self._per_key.get(key, 0)

    def shutdown(self) -> None:
        """Stop the lanes once their current work is done (app shutdown)."""
        distinct = {id(lane): lane for lane in self._lanes.values()}  # the site lane may be the light one
        for lane in distinct.values():
            lane.shutdown()
