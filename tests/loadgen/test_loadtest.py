"""``edgepos loadtest``: loopback only, bounded, and a tiny load against a real server."""

from __future__ import annotations

import json
import socket
import time

import pytest
from edgepos.cli import main
from loadgenhelp import ADMIN_KEY


@pytest.fixture
def connection_attempts(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every attempt to resolve a host name or open a connection, refused and recorded."""
    attempts: list[str] = []

    def refuse(what: str):
        def refused(*args, **kwargs):
            attempts.append(f"{what}{args[-1:]!r}")
            raise ConnectionRefusedError(f"test: no {what} allowed")

        return refused

    for name in ("connect", "connect_ex"):
        monkeypatch.setattr(socket.socket, name, refuse(f"socket.{name}"))
    monkeypatch.setattr(socket, "create_connection", refuse("create_connection"))
    monkeypatch.setattr(socket, "getaddrinfo", refuse("getaddrinfo"))
    return attempts


@pytest.mark.parametrize("url", ["http://192.168.1.10:8000", "http://example.com", "http://0.0.0.0:8000"])
def test_refuses_non_loopback_urls(url: str, capsys, connection_attempts: list[str]) -> None:
    argv = ["loadtest", "--url", url, "--vehicles", "1", "--rate", "20", "--batch", "20", "--duration", "1"]
    assert main(argv) == 2
    assert "not loopback" in capsys.readouterr().err
    assert connection_attempts == []  # refused before any look-up or connection attempt


def test_refuses_unbounded_or_empty_runs(capsys) -> None:
    argv = [
        "loadtest",
        "--url",
        "http://127.0.0.1:9",
        "--vehicles",
        "0",
        "--rate",
        "0",
        "--batch",
        "20",
        "--duration",
        "7200",
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--vehicles" in err and "--rate" in err and "--duration" in err


@pytest.mark.slow
def test_tiny_bounded_load_has_no_errors(server_url: str, tmp_path, capsys) -> None:
    out = tmp_path / "load.json"
    argv = [
        "loadtest",
        "--url",
        server_url,
        "--admin-key",
        ADMIN_KEY,
        "--vehicles",
        "2",
        "--rate",
        "20",
        "--batch",
        "10",
        "--duration",
        "3",
        "--json",
        str(out),
    ]
    started = time.perf_counter()
    assert main(argv) == 0
    # Bounded: 3 s of sending, then at most the one batch in flight per vehicle (10 s request timeout)
    # and the sessions' set-up and clean-up; a generous margin for a busy machine on top.
    assert time.perf_counter() - started < 60.0
    report = json.loads(out.read_text())
    assert {"epochs_per_s", "requests_per_s", "requests", "errors", "latency_ms"} <= set(report)
    assert set(report["latency_ms"]) == {"p50", "p95", "p99"}
    assert report["errors"] == 0
    # 2 vehicles x one batch per 0.5 s x 3 s are due; each is sent or, when a busy machine made the
    # vehicle fall behind its schedule, counted as unsent (the schedule itself is checked exactly
    # against a virtual clock below).
    assert report["requests"] + report["lateness"]["unsent_batches"] == 12
    assert report["requests"] >= 2
    assert report["epochs"] == 10 * report["requests"]
    assert 0 < report["latency_ms"]["p50"] <= report["latency_ms"]["p95"] <= report["latency_ms"]["p99"]
    assert report["epochs_per_s"] == pytest.approx(report["epochs"] / report["elapsed_s"])
    printed = capsys.readouterr().out
    assert "epochs/s" in printed and "p99" in printed and "lateness" in printed
    assert "trips restarted 0 (vehicles that reached the scenario's end and reopened a session)" in printed


class FakeClient:
    """Stands in for the async client: records calls; batch ``fail_on`` (1-based) raises a 409."""

    def __init__(self, fail_on: int | None = None) -> None:
        self.calls: list[str] = []
        self.fail_on = fail_on
        self.sent = 0

    async def create_session(self, vehicle_id, pipeline="rsu_imu", *, options=None, initial_state=None):
        from edgepos_client import Session

        self.calls.append("create")
        return Session(f"s{len(self.calls)}", "token")

    async def delete_session(self, session) -> None:
        self.calls.append("delete")

    async def send_batch(self, session, measurements, seq=None, *, include_state=False):
        from edgepos_client import Conflict

        self.sent += 1
        self.calls.append("batch")
        if self.sent == self.fail_on:
            raise Conflict("conflict", "seq out of order", status=409)
        session.last_seq += 1
        return [object()] * len(measurements)


def _vehicle(client: FakeClient, batches: int):
    from edgepos.loadgen.loadtest import Recorder, Vehicle
    from edgepos.sim.scenarios import rsu_imu_paper_scenario

    recorder = Recorder()
    return Vehicle(0, client, [[None]] * batches, rsu_imu_paper_scenario(), recorder), recorder


def test_vehicle_starts_a_new_trip_at_the_end_of_the_scenario() -> None:
    import asyncio

    client = FakeClient()
    vehicle, recorder = _vehicle(client, batches=2)

    async def drive() -> None:
        for _ in range(5):
            await vehicle.send_one()

    asyncio.run(drive())
    assert client.calls == [
        "create",
        "batch",
        "batch",
        "delete",
        "create",
        "batch",
        "batch",
        "delete",
        "create",
        "batch",
    ]
    assert (recorder.requests, recorder.epochs, recorder.trips, sum(recorder.errors.values())) == (5, 5, 3, 0)


def test_vehicle_counts_an_error_and_resynchronises() -> None:
    import asyncio

    client = FakeClient(fail_on=2)
    vehicle, recorder = _vehicle(client, batches=10)

    async def drive() -> None:
        for _ in range(3):
            await vehicle.send_one()

    asyncio.run(drive())
    assert client.calls == [
        "create",
        "batch",
        "batch",
        "delete",
        "create",
        "batch",
    ]  # the failed session is closed
    assert recorder.errors == {"conflict": 1} and recorder.requests == 3 and len(recorder.latencies_ms) == 2


class VirtualClock:
    """A clock that only moves when someone sleeps: the schedule logic runs the same on a busy machine."""

    def __init__(self) -> None:
        self.time = 0.0

    def now(self) -> float:
        return self.time

    async def sleep(self, seconds: float) -> None:
        import asyncio

        self.time += max(0.0, seconds)
        await asyncio.sleep(0)


def _run_open_loop(service_s: float, rate: float, duration: float, offset: float = 0.0):
    """One vehicle, 1-epoch batches, against a fake server that takes ``service_s`` per batch."""
    import asyncio

    from edgepos.loadgen.loadtest import LoadConfig

    clock = VirtualClock()

    class SlowClient(FakeClient):
        async def send_batch(self, session, measurements, seq=None, *, include_state=False):
            await clock.sleep(service_s)
            return await super().send_batch(session, measurements, seq, include_state=include_state)

    vehicle, recorder = _vehicle(SlowClient(), batches=1000)
    vehicle.clock = clock
    config = LoadConfig(url="http://127.0.0.1:1", vehicles=1, rate=rate, batch=1, duration=duration)
    asyncio.run(vehicle.run(config, clock.now(), offset))
    return clock, recorder


def test_a_vehicle_behind_schedule_stops_at_the_end_and_counts_what_it_did_not_send() -> None:
    """Open loop against a server slower than the offered rate: the run stays bounded by its duration."""
    clock, recorder = _run_open_loop(service_s=0.1, rate=50.0, duration=0.5)  # 10 batches/s against 50
    assert clock.now() == pytest.approx(0.5)
    assert recorder.requests == 5
    assert recorder.unsent == 20  # every due batch (25) is either sent or counted as unsent
    assert recorder.late_waiting_server == 4 and recorder.late_generator == 0


def test_a_vehicle_on_schedule_sends_every_due_batch_and_nothing_more() -> None:
    clock, recorder = _run_open_loop(service_s=0.001, rate=50.0, duration=0.5, offset=0.01)
    assert recorder.requests == 25 and recorder.unsent == 0
    assert recorder.late_waiting_server == recorder.late_generator == 0
    assert clock.now() < 0.5


@pytest.mark.parametrize(
    ("duration", "offset", "interval", "due"),
    [(0.5, 0.0, 0.02, 25), (0.5, 0.1, 0.02, 20), (0.3, 0.0, 0.1, 3), (1.0, 0.0, 0.3, 4), (0.5, 0.5, 0.1, 0)],
)
def test_batches_due_counts_a_due_time_on_the_end_as_outside(duration, offset, interval, due) -> None:
    from edgepos.loadgen.loadtest import batches_due

    assert batches_due(duration, offset, interval) == due


REMOTE = "http://192.0.2.7:8000"  # TEST-NET-1 (RFC 5737): never routed; and no test ever connects to it


def test_the_refusal_names_the_flag_for_a_deployment_one_owns(capsys, connection_attempts: list[str]) -> None:
    argv = [
        "loadtest",
        "--url",
        REMOTE,
        "--vehicles",
        "1",
        "--rate",
        "20",
        "--batch",
        "20",
        "--duration",
        "1",
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "not loopback" in err and "pass --allow-remote" in err
    assert connection_attempts == []


def test_allow_remote_lifts_only_the_loopback_guard() -> None:
    """Checked on the configuration alone: nothing here connects anywhere."""
    from edgepos.loadgen.loadtest import LoadConfig

    config = LoadConfig(url=REMOTE, vehicles=1, rate=20.0, batch=20, duration=1.0, admin_key="k")
    assert any("not loopback" in problem and "--allow-remote" in problem for problem in config.problems())
    allowed = LoadConfig(
        url=REMOTE, vehicles=1, rate=20.0, batch=20, duration=1.0, admin_key="k", allow_remote=True
    )
    assert allowed.problems() == []
    warning = allowed.remote_warning()
    assert warning is not None and "192.0.2.7" in warning and "own" in warning
    # the other checks stay: a malformed or non-HTTP URL and an unbounded run are still refused
    for bad in ("ftp://192.0.2.7", "192.0.2.7:8000", "http://192.0.2.7:99999"):
        assert LoadConfig(
            url=bad, vehicles=1, rate=20.0, batch=20, duration=1.0, admin_key="k", allow_remote=True
        ).problems()
    unbounded = LoadConfig(
        url=REMOTE, vehicles=1, rate=20.0, batch=20, duration=7200.0, admin_key="k", allow_remote=True
    )
    assert unbounded.problems() == ["--duration must be in (0, 3600] s"]
    loopback = LoadConfig(
        url="http://127.0.0.1:9",
        vehicles=1,
        rate=20.0,
        batch=20,
        duration=1.0,
        admin_key="k",
        allow_remote=True,
    )
    assert loopback.problems() == [] and loopback.remote_warning() is None


def test_allow_remote_parses_and_reaches_the_configuration(capsys, connection_attempts: list[str]) -> None:
    """With the flag the command gets past the guard to the next check (here: no admin key), still
    before any connection."""
    argv = [
        "loadtest",
        "--url",
        REMOTE,
        "--allow-remote",
        "--vehicles",
        "1",
        "--rate",
        "20",
        "--batch",
        "20",
        "--duration",
        "1",
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "not loopback" not in err and "admin key" in err
    assert connection_attempts == []


def test_help_explains_the_trips_and_the_remote_flag(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["loadtest", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "'trips restarted' counts the vehicles that reached the end of the scenario" in out
    assert "--allow-remote" in out and "deployment you own" in out


def test_the_rsu_map_is_loaded_with_the_vehicles_retries(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 503 while the service warms up (Redis Cluster under load) must not end the run before it starts:
    the admin call that loads the RSU map retries as the vehicles' calls do."""
    import asyncio
    from typing import Self

    from edgepos.loadgen import loadtest
    from edgepos_client import EdgeposError

    built: list[int] = []

    class Answering503:
        def __init__(self, url: str, key: str | None, *, timeout: float, retries: int, **_: object) -> None:
            built.append(retries)

        async def __aenter__(self) -> Self:
            return self

        async def __aexit__(self, *_: object) -> None:
            return None

        async def put_rsus(self, rsus: object) -> int:
            raise EdgeposError("unavailable", "the session store does not answer", status=503)

    monkeypatch.setattr(loadtest, "AsyncEdgeposClient", Answering503)
    config = loadtest.LoadConfig(
        url="http://127.0.0.1:9", vehicles=1, rate=1.0, batch=1, duration=1.0, admin_key=ADMIN_KEY, retries=4
    )
    with pytest.raises(EdgeposError):
        asyncio.run(loadtest.run_load(config))
    assert built == [4]
