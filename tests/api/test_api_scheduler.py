"""The fair scheduler: vehicles served in turn, a bounded line per vehicle, heavy jobs in a worker
process that cannot hold this interpreter's lock, and a worker that dies replaced by a fresh one; the
light lane on the event loop (the default) or on a thread, the site's work always on a thread.

Orders are checked with events, never with sleeps or timings: a job that must not start yet waits
on an event the test sets."""

from __future__ import annotations

import asyncio
import functools
import os
import threading

import pytest
from edgepos.api.errors import ApiError
from edgepos.api.metrics import Metrics
from edgepos.api.scheduler import FairScheduler, LightLane, _Job, _RoundRobin, _timed


def _record(order: list[str], name: str, gate: threading.Event | None = None) -> str:
    if gate is not None:
        assert gate.wait(30), "the test never opened the gate"
    order.append(name)
    return name


def test_vehicles_are_served_in_turn_not_in_arrival_order() -> None:
    """While the lane is busy, A queues three jobs and then B one: B's runs second, not fourth."""

    async def scenario() -> list[str]:
        scheduler = FairScheduler(Metrics(), heavy_workers=0, light_lane="thread")
        order: list[str] = []
        gate = threading.Event()
        blocker = asyncio.ensure_future(scheduler.run("Z", 0.0, "test", _record, order, "Z", gate))
        await asyncio.sleep(0)
        jobs = [
            asyncio.ensure_future(scheduler.run("A", 0.0, "test", _record, order, f"A{n}")) for n in (1, 2, 3)
        ]
        jobs.append(asyncio.ensure_future(scheduler.run("B", 0.0, "test", _record, order, "B1")))
        await asyncio.sleep(0)
        gate.set()
        await asyncio.gather(blocker, *jobs)
        scheduler.shutdown()
        return order

    assert asyncio.run(scenario()) == ["Z", "A1", "B1", "A2", "A3"]


def test_the_light_lane_runs_the_next_job_without_waiting_for_the_event_loop() -> None:
    """Three vehicles' jobs queued, then the event loop blocked: the lane's thread runs all three in
    turn by itself. (Fed one job at a time by the loop, it would run only the first: two thread
    wake-ups per job, the cost bench/scheduler_overhead.py measures.)"""

    async def scenario() -> list[str]:
        scheduler = FairScheduler(Metrics(), heavy_workers=0, light_lane="thread")
        order: list[str] = []
        gate = threading.Event()
        all_ran = threading.Event()

        def job(name: str) -> str:
            _record(order, name, gate if name == "A" else None)
            if len(order) == 3:
                all_ran.set()
            return name

        jobs = [asyncio.ensure_future(scheduler.run(key, 0.0, "test", job, key)) for key in ("A", "B", "C")]
        await asyncio.sleep(0)  # the three are queued; A's waits on the gate
        gate.set()
        ran_while_blocked = all_ran.wait(30)  # the loop blocks here: it cannot hand out B and C
        results = await asyncio.gather(*jobs)
        scheduler.shutdown()
        assert ran_while_blocked, "the lane's thread waited for the event loop between jobs"
        assert results == ["A", "B", "C"]
        return order

    assert asyncio.run(scenario()) == ["A", "B", "C"]


def test_on_the_loop_jobs_that_arrive_together_are_served_in_turn() -> None:
    """The loop lane takes every job through its line: Z, three of A's and one of B's, all ready in
    the same turn of the loop, run Z, A1, B1, A2, A3 (arrival order would put B1 last)."""

    async def scenario() -> list[str]:
        scheduler = FairScheduler(Metrics(), heavy_workers=0, light_lane="loop")
        order: list[str] = []
        keys = [("Z", "Z"), ("A", "A1"), ("A", "A2"), ("A", "A3"), ("B", "B1")]
        jobs = [
            asyncio.ensure_future(scheduler.run(key, 0.0, "test", _record, order, name)) for key, name in keys
        ]
        await asyncio.gather(*jobs)
        scheduler.shutdown()
        return order

    assert asyncio.run(scenario()) == ["Z", "A1", "B1", "A2", "A3"]


def test_the_loop_lane_runs_jobs_on_the_loop_and_serves_the_loop_between_two() -> None:
    """Each job runs on the event loop's thread, and a callback the first one schedules runs before
    the second job: the loop reads its sockets between two jobs, not after the whole line."""

    async def scenario() -> tuple[list[str], set[int]]:
        loop = asyncio.get_running_loop()
        scheduler = FairScheduler(Metrics(), heavy_workers=0, light_lane="loop")
        order: list[str] = []
        threads: set[int] = set()

        def job(name: str) -> str:
            threads.add(threading.get_ident())
            if name == "A":
                loop.call_soon(order.append, "callback")
            order.append(name)
            return name

        jobs = [asyncio.ensure_future(scheduler.run(key, 0.0, "test", job, key)) for key in ("A", "B")]
        await asyncio.gather(*jobs)
        scheduler.shutdown()
        return order, threads

    order, threads = asyncio.run(scenario())
    assert order == ["A", "callback", "B"]
    assert threads == {threading.get_ident()}  # asyncio.run's loop runs on this thread


def test_a_request_that_went_away_leaves_its_job_unrun() -> None:
    async def scenario() -> list[str]:
        scheduler = FairScheduler(Metrics(), heavy_workers=0, light_lane="loop")
        order: list[str] = []
        gone = asyncio.ensure_future(scheduler.run("A", 0.0, "test", _record, order, "A"))
        kept = asyncio.ensure_future(scheduler.run("B", 0.0, "test", _record, order, "B"))
        await asyncio.sleep(0)  # both queued, neither run: the lane serves on the next turn of the loop
        gone.cancel()
        assert await kept == "B"
        scheduler.shutdown()
        return order

    assert asyncio.run(scenario()) == ["B"]


@pytest.mark.parametrize("light_lane", ["loop", "thread"])
def test_the_sites_work_never_runs_on_the_loop(light_lane: LightLane) -> None:
    """Kernel warm-up and file parsing have no predicted cost: always a thread, the light lane's own
    when it has one."""

    async def scenario() -> tuple[int, int]:
        scheduler = FairScheduler(Metrics(), heavy_workers=0, light_lane=light_lane)
        site = await scheduler.run_site(threading.get_ident)
        light = await scheduler.run("car", 0.0, "test", threading.get_ident)
        scheduler.shutdown()
        return site, light

    site, light = asyncio.run(scenario())
    assert site != threading.get_ident()
    assert (light == site) == (light_lane == "thread")


def test_a_vehicle_holds_a_bounded_number_of_places() -> None:
    async def scenario() -> None:
        metrics = Metrics()
        scheduler = FairScheduler(metrics, max_queued_per_key=2, heavy_workers=0)
        async with scheduler.hold("car"), scheduler.hold("car"):
            with pytest.raises(ApiError) as refused:
                async with scheduler.hold("car"):
                    pass
            assert refused.value.status == 429 and refused.value.headers["Retry-After"] == "1"
            assert "EDGEPOS_MAX_QUEUED_PER_VEHICLE" in refused.value.message
            async with scheduler.hold("bus"):  # another vehicle has its own line
                assert scheduler.held("bus") == 1
        assert scheduler.held("car") == 0
        async with scheduler.hold("car"):  # places come back when requests end
            pass
        scheduler.shutdown()

    asyncio.run(scenario())


@pytest.mark.parametrize("light_lane", ["loop", "thread"])
def test_light_and_heavy_jobs_take_separate_lanes(light_lane: LightLane) -> None:
    """A heavy job stuck in its lane (a thread here) does not hold up a light one."""

    async def scenario() -> list[str]:
        scheduler = FairScheduler(Metrics(), slice_s=0.010, heavy_workers=0, light_lane=light_lane)
        assert scheduler.lane_for(0.010) == "light" and scheduler.lane_for(0.011) == "heavy"
        order: list[str] = []
        gate = threading.Event()
        heavy = asyncio.ensure_future(scheduler.run("truck", 1.0, "test", _record, order, "heavy", gate))
        light = await scheduler.run("car", 0.001, "test", _record, order, "light")
        gate.set()
        await heavy
        scheduler.shutdown()
        assert light == "light"
        return order

    assert asyncio.run(scenario()) == ["light", "heavy"]


@pytest.mark.parametrize("light_lane", ["loop", "thread"])
def test_heavy_jobs_run_in_a_worker_process_and_count_their_cpu(light_lane: LightLane) -> None:
    async def scenario() -> tuple[int, int, float]:
        metrics = Metrics()
        scheduler = FairScheduler(metrics, slice_s=0.0, heavy_workers=1, light_lane=light_lane)
        heavy_pid = await scheduler.run("truck", 1.0, "gnss_tight", os.getpid)
        light_pid = await scheduler.run("car", 0.0, "rsu_imu", os.getpid)
        scheduler.shutdown()
        cpu = metrics.pipeline_cpu.labels("gnss_tight")._value.get()
        return heavy_pid, light_pid, cpu

    heavy_pid, light_pid, cpu = asyncio.run(scenario())
    assert heavy_pid != os.getpid()
    assert light_pid == os.getpid()
    assert cpu >= 0.0


def test_a_worker_that_dies_fails_its_job_with_503_and_is_replaced() -> None:
    async def scenario() -> int:
        scheduler = FairScheduler(Metrics(), slice_s=0.0, heavy_workers=1)
        with pytest.raises(ApiError) as failed:
            await scheduler.run("truck", 1.0, "test", os._exit, 3)
        assert failed.value.status == 503
        pid = await scheduler.run("truck", 1.0, "test", os.getpid)  # a fresh pool answers
        scheduler.shutdown()
        return pid

    assert asyncio.run(scenario()) != os.getpid()


@pytest.mark.parametrize("light_lane", ["loop", "thread"])
def test_an_error_in_a_job_reaches_the_caller_unchanged(light_lane: LightLane) -> None:
    async def scenario() -> None:
        scheduler = FairScheduler(Metrics(), heavy_workers=0, light_lane=light_lane)
        with pytest.raises(ZeroDivisionError):
            await scheduler.run("car", 0.0, "test", divmod, 1, 0)
        assert await scheduler.run("car", 0.0, "test", divmod, 7, 2) == (3, 1)  # the lane goes on
        scheduler.shutdown()

    asyncio.run(scenario())


def _heavy_worker_pid() -> int:
    """Start a scheduler with a heavy worker in this (child) process, print the worker's pid, then
    die without any shutdown, as a SIGKILLed service would."""

    async def scenario() -> int:
        scheduler = FairScheduler(Metrics(), slice_s=0.0, heavy_workers=1)
        return await scheduler.run("truck", 1.0, "test", os.getpid)

    pid = asyncio.run(scenario())
    print(pid, flush=True)
    os._exit(0)


def test_a_heavy_worker_does_not_outlive_a_killed_service() -> None:
    """The worker process notices its parent is gone and exits by itself (checked every second)."""
    import subprocess
    import sys
    import time

    code = "import test_api_scheduler as t; t._heavy_worker_pid()"
    here = os.path.dirname(os.path.abspath(__file__))
    child = subprocess.run(
        [sys.executable, "-c", code],
        cwd=here,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        env={**os.environ, "PYTHONPATH": here + os.pathsep + os.environ.get("PYTHONPATH", "")},
    )
    worker = int(child.stdout.strip().splitlines()[-1])
    deadline = time.monotonic() + 60.0  # a bounded wait for a condition, not a timing assertion
    while time.monotonic() < deadline:
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            return
        time.sleep(0.2)
    os.kill(worker, 9)
    raise AssertionError(f"heavy worker {worker} outlived its service by 60 s")


def test_the_lines_depth_counts_the_jobs_waiting_as_they_come_and_go() -> None:
    """``depth()`` (a count kept by push, pop and drain) is the number of jobs waiting in every key's line."""

    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        line = _RoundRobin()

        def job(key: str) -> _Job:
            return _Job(key, "test", functools.partial(_timed, int), loop.create_future(), loop, 0.0)

        def waiting() -> int:
            return sum(len(jobs) for jobs in line.waiting.values())

        for key in ("A", "B", "A", "C", "A", "B"):
            line.push(job(key))
            assert line.depth() == waiting()
        assert line.depth() == 6
        for _ in range(4):
            assert line.pop() is not None
            assert line.depth() == waiting()
        line.push(job("D"))
        assert line.depth() == waiting() == 3
        assert len(line.drain()) == 3 and line.depth() == 0
        assert line.pop() is None and line.depth() == 0

    asyncio.run(scenario())
