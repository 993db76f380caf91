"""``edgepos loadtest``: loopback only, bounded, and a tiny load against a real server."""

from __future__ import annotations

import json
import time

import pytest
from edgepos.cli import main
from loadgenhelp import ADMIN_KEY


@pytest.mark.parametrize("url", ["http://192.168.1.10:8000", "http://example.com", "http://0.0.0.0:8000"])
def test_refuses_non_loopback_urls(url: str, capsys) -> None:
    argv = ["loadtest", "--url", url, "--vehicles", "1", "--rate", "20", "--batch", "20", "--duration", "1"]
    started = time.perf_counter()
    assert main(argv) == 2
    assert "not loopback" in capsys.readouterr().err
    assert time.perf_counter() - started < 5.0  # refused before any connection attempt


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
    assert time.perf_counter() - started < 20.0
    report = json.loads(out.read_text())
    assert {"epochs_per_s", "requests_per_s", "requests", "errors", "latency_ms"} <= set(report)
    assert set(report["latency_ms"]) == {"p50", "p95", "p99"}
    assert report["errors"] == 0
    assert 8 <= report["requests"] <= 14  # 2 vehicles x one batch per 0.5 s x 3 s
    assert report["epochs"] == 10 * report["requests"]
    assert 0 < report["latency_ms"]["p50"] <= report["latency_ms"]["p95"] <= report["latency_ms"]["p99"]
    assert report["epochs_per_s"] == pytest.approx(report["epochs"] / report["elapsed_s"])
    printed = capsys.readouterr().out
    assert "epochs/s" in printed and "p99" in printed and "lateness" in printed


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
    return Vehicle(0, client, [[None]] * batches, rsu_imu_paper_scenario(), recorder), recorder  # type: ignore[arg-type]


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


def test_a_vehicle_behind_schedule_stops_at_the_end_and_counts_what_it_did_not_send() -> None:
    """Open loop against a server slower than the offered rate: the run stays bounded by its duration."""
    import asyncio

    from edgepos.loadgen.loadtest import LoadConfig

    class SlowClient(FakeClient):
        async def send_batch(self, session, measurements, seq=None, *, include_state=False):
            await asyncio.sleep(0.1)  # 10 batches/s at most, against 50 offered
            return await super().send_batch(session, measurements, seq, include_state=include_state)

    client = SlowClient()
    vehicle, recorder = _vehicle(client, batches=1000)
    config = LoadConfig(url="http://127.0.0.1:1", vehicles=1, rate=50.0, batch=1, duration=0.5)
    started = time.perf_counter()
    asyncio.run(vehicle.run(config, started, 0.0))
    elapsed = time.perf_counter() - started
    assert elapsed < 0.75
    assert 4 <= recorder.requests <= 6
    assert recorder.requests + recorder.unsent == 25  # every due batch is either sent or counted as unsent
