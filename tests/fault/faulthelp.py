"""Helpers of the fault tests: a real ``edgepos serve`` process whose workers can be listed and
killed, and the paper scenario's batches with an in-process reference to check served state against."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
from edgepos.core.observations import Observation
from edgepos.loadgen import common
from edgepos.loadgen.loadtest import LoadConfig, LoadReport, run_load
from edgepos.loadgen.localserver import free_port
from edgepos.pipelines.base import InitialState, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.delivery import LateDelivery, arrival_batches, arrival_times
from edgepos.sim.scenarios import Scenario, rsu_imu_paper_scenario
from edgepos_client import InitialState as WireInitialState

ADMIN_KEY = "fault-admin-key-9c1e7a53b2d04f68"
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
#: How long a server (or a replacement worker) may take to be ready (s). Each worker compiles the filter
#: kernels at start-up unless numba's cache has them: over a minute on a busy 2-core machine from a
#: fresh clone, with two workers compiling at once.
SERVER_READY_S = 300.0


@dataclass
class Server:
    url: str
    process: subprocess.Popen[bytes]
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    @property
    def port(self) -> int:
        return int(self.url.rsplit(":", 1)[1])

    def worker_pids(self) -> list[int]:
        """The uvicorn worker processes (spawned children running ``spawn_main``)."""
        return worker_pids(self.process.pid)

    def connections_by_worker(self) -> dict[int, int]:
        """How many established client connections each worker holds right now."""
        established = _established_inodes(self.port)
        counts = {}
        for pid in self.worker_pids():
            held = 0
            with contextlib.suppress(OSError):
                for fd in Path(f"/proc/{pid}/fd").iterdir():
                    with contextlib.suppress(OSError):
                        target = os.readlink(fd)
                        held += target.startswith("socket:[") and target[8:-1] in established
            counts[pid] = held
        return counts


def _established_inodes(port: int) -> set[str]:
    """Socket inodes of established TCP connections whose local port is ``port`` (/proc/net/tcp)."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError):
            for line in Path(table).read_text().splitlines()[1:]:
                fields = line.split()
                if int(fields[1].rsplit(":", 1)[1], 16) == port and fields[3] == "01":
                    inodes.add(fields[9])
    return inodes


def worker_pids(parent: int) -> list[int]:
    pids = []
    for task in Path(f"/proc/{parent}/task").iterdir():
        with contextlib.suppress(OSError):
            pids.extend(int(pid) for pid in (task / "children").read_text().split())
    workers = []
    for pid in pids:
        with contextlib.suppress(OSError):
            if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes():
                workers.append(pid)
    return sorted(workers)


@contextlib.contextmanager
def serve(tmp_path: Path, workers: int, **env: str) -> Iterator[Server]:
    """``edgepos serve --workers N`` on a free loopback port with the given EDGEPOS_* settings;
    waits for /readyz, stops the whole process group afterwards."""
    port = free_port()
    environment = {k: v for k, v in os.environ.items() if not k.startswith("EDGEPOS_")}
    environment.update({"EDGEPOS_ADMIN_KEY": ADMIN_KEY, "EDGEPOS_LOG_LEVEL": "warning", **env})
    log_path = tmp_path / f"server-{port}.log"
    command = [sys.executable, "-m", "edgepos.cli", "serve", "--host", "127.0.0.1", "--port", str(port)]
    with open(log_path, "wb") as log:
        process = subprocess.Popen(
            [*command, "--workers", str(workers)],
            env=environment,
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=tmp_path,
            start_new_session=True,
        )
    server = Server(f"http://127.0.0.1:{port}", process, log_path)
    try:
        wait_ready(server, SERVER_READY_S, workers)
        yield server
    finally:
        process.terminate()
        try:
            process.wait(timeout=20.0)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, 9)
            process.wait()


def wait_ready(server: Server, timeout_s: float, workers: int | None = None) -> None:
    """Until /readyz is 200 (and, when given, ``workers`` workers exist)."""
    deadline = time.monotonic() + timeout_s
    while True:
        assert server.process.poll() is None, server.log()
        with contextlib.suppress(httpx.HTTPError):
            ready = httpx.get(f"{server.url}/readyz", timeout=1.0).status_code == 200
            if ready and (workers is None or workers == 1 or len(server.worker_pids()) == workers):
                return
        assert time.monotonic() < deadline, f"server not ready within {timeout_s} s:\n{server.log()[-3000:]}"
        time.sleep(0.1)


@functools.lru_cache(maxsize=1)
def scenario() -> Scenario:
    return rsu_imu_paper_scenario()


def start_state() -> WireInitialState:
    return common.initial_state(scenario())


LATE = LateDelivery(fraction=0.3, max_delay_s=0.5)
"""With ``late=True``: 30 % of the RSU measurements arrive 0.05-0.5 s late, so that batches carry late
measurements the lag window replays (seeded per stream)."""


@functools.lru_cache(maxsize=16)
def _observation_batches(stream: int, batch_epochs: int, late: bool) -> tuple[tuple[Observation, ...], ...]:
    epochs = common.vehicle_epochs(scenario(), 0, stream)
    if not late:
        return tuple(
            tuple(o for epoch in epochs[k : k + batch_epochs] for o in epoch)
            for k in range(0, len(epochs), batch_epochs)
        )
    observations = [o for epoch in epochs for o in epoch]
    arrivals = arrival_times(observations, LATE, np.random.default_rng([stream, 15]))
    return tuple(tuple(batch) for batch in arrival_batches(observations, arrivals, batch_epochs))


@functools.lru_cache(maxsize=16)
def stream_batches(
    stream: int, batch_epochs: int, late: bool = False
) -> tuple[list[common.WireMeasurement], ...]:
    """Noise stream ``stream``'s measurements in batches of ``batch_epochs`` epochs (client models); with
    ``late`` as they would arrive with :data:`LATE` (each batch what arrived since the previous one)."""
    return tuple(
        [common.to_wire(o) for o in batch] for batch in _observation_batches(stream, batch_epochs, late)
    )


def reference_states(stream: int, batch_epochs: int, batches: int, late: bool = False) -> list[bytes]:
    """The in-process pipeline's state after 0, 1, ..., ``batches`` batches of the stream (as
    :func:`stream_batches` cuts it), from the same start and default options as a session opened with
    :func:`start_state`."""
    pipeline = get_pipeline("rsu_imu")
    environment = StaticEnvironment({rsu.id: rsu for rsu in scenario().rsus})
    start = start_state()
    state = pipeline.create(pipeline.resolve_options({}), InitialState(**start.model_dump()))
    states = [state]
    for observations in _observation_batches(stream, batch_epochs, late)[:batches]:
        _fixes, state = pipeline.process(state, list(observations), environment)
        states.append(state)
    return states


def load_with_fault(
    config: LoadConfig,
    due: Callable[[float], bool],
    fault: Callable[[], None] | None,
    server: Server,
    timeout_s: float = 180.0,
) -> LoadReport:
    """``config``'s load test in a thread; ``fault()`` runs once ``due(seconds since the start)`` is true.
    Asserts the load outlived the fault, ended within ``timeout_s`` after its duration and that the
    service was never restarted."""
    result: dict[str, object] = {}

    def load() -> None:
        try:
            result["report"] = asyncio.run(run_load(config))
        except Exception as error:  # noqa: BLE001  (any failure of the load thread is reported below)
            result["error"] = error

    worker = threading.Thread(target=load, daemon=True)
    started = time.monotonic()
    worker.start()
    if fault is not None:
        while not due(time.monotonic() - started):
            assert worker.is_alive(), result.get("error")
            time.sleep(0.05)
        assert worker.is_alive(), "the load ended before the fault"
        fault()
    worker.join(config.duration + timeout_s)
    assert not worker.is_alive()
    assert server.process.poll() is None  # the service was never restarted
    assert "error" not in result, result.get("error")
    report = result["report"]
    assert isinstance(report, LoadReport)
    return report
