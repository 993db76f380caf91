"""``edgepos simulate`` end to end against a real server process, and its fixes equal the
in-process pipeline's bit for bit on the same observations."""

from __future__ import annotations

import asyncio
import json

import pytest
from edgepos.cli import main
from edgepos.loadgen import common
from edgepos.loadgen.localserver import clean_environment, running, serve_command
from edgepos.loadgen.simulate import run_simulation
from edgepos.pipelines.base import InitialState
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment
from loadgenhelp import ADMIN_KEY

pytestmark = pytest.mark.slow


def test_cli_reports_rmse_per_vehicle(server_url, tmp_path, capsys) -> None:
    out = tmp_path / "results" / "sim.json"  # --json creates the directory it names
    argv = [
        "simulate",
        "--url",
        server_url,
        "--admin-key",
        ADMIN_KEY,
        "--epochs",
        "120",
        "--batch-epochs",
        "25",
        "--seed",
        "3",
        "--json",
        str(out),
    ]
    assert main(argv) == 0
    printed = capsys.readouterr()
    assert "simulate: 1 vehicle(s), 120/120 epochs (100 %)" in printed.err
    assert "sim-1" in printed.out and "mean" in printed.out
    result = json.loads(out.read_text())
    (vehicle,) = result["vehicles"]
    assert vehicle["fixes"] == 120 and vehicle["error"] is None
    assert 0 < vehicle["position_rmse_m"] < 2.0 and 0 < vehicle["velocity_rmse_m_s"] < 3.0
    assert result["mean"]["position_rmse_m"] == vehicle["position_rmse_m"]


def test_cli_json_under_a_file_is_refused_before_any_request(tmp_path, capsys) -> None:
    (tmp_path / "results").write_text("not a directory")
    argv = ["simulate", "--url", "http://127.0.0.1:9", "--admin-key", ADMIN_KEY]
    assert main([*argv, "--json", str(tmp_path / "results" / "sim.json")]) == 2
    assert "--json: cannot create the directory" in capsys.readouterr().err


def test_cli_needs_the_admin_key(server_url, monkeypatch, capsys) -> None:
    monkeypatch.delenv("EDGEPOS_ADMIN_KEY", raising=False)
    assert main(["simulate", "--url", server_url]) == 2
    assert "--admin-key" in capsys.readouterr().err


def test_http_fixes_equal_the_in_process_pipeline(server_url) -> None:
    epochs, batch_epochs, seed = 90, 20, 11
    result = asyncio.run(
        run_simulation(
            server_url, vehicles=2, admin_key=ADMIN_KEY, seed=seed, batch_epochs=batch_epochs, epochs=epochs
        )
    )
    scenario = rsu_imu_paper_scenario()
    pipeline = get_pipeline("rsu_imu")
    start = common.initial_state(scenario)
    for vehicle in result.vehicles:
        assert vehicle.error is None
        observations = common.vehicle_epochs(scenario, seed, vehicle.index)[:epochs]
        state = pipeline.create(pipeline.resolve_options(None), InitialState(**start.model_dump()))
        expected = []
        for first in range(0, epochs, batch_epochs):
            batch = [o for epoch in observations[first : first + batch_epochs] for o in epoch]
            fixes, state = pipeline.process(state, batch, environment(scenario))
            expected.extend(fixes)
        assert len(vehicle.fixes) == len(expected) == epochs
        for got, want in zip(vehicle.fixes, expected):
            assert (
                got.t,
                got.status,
                got.x,
                got.y,
                got.vx,
                got.vy,
                got.speed,
                got.heading,
                got.yaw_rate,
            ) == (
                want.t,
                want.status,
                want.x,
                want.y,
                want.vx,
                want.vy,
                want.speed,
                want.heading,
                want.yaw_rate,
            )
            assert got.position_covariance == want.position_cov
            assert got.model_probabilities == want.model_probabilities
            assert (got.nis, got.nis_dof) == (want.nis, want.nis_dof)
            assert [(m.index, m.type, m.used, m.reason) for m in got.measurements] == [
                (m.index, m.kind, m.used, m.reason) for m in want.measurements
            ]
    assert result.vehicles[0].fixes != result.vehicles[1].fixes  # each vehicle its own noise


def test_cli_late_delivery_matches_in_order_and_beats_dropping(server_url, tmp_path, capsys) -> None:
    """--delay-fraction runs in order, late and dropped over HTTP; the last fix per epoch of the late run
    equals the in-order run's (replay is exact), dropping the late measurements is worse."""
    out = tmp_path / "late.json"
    argv = [
        "simulate",
        "--url",
        server_url,
        "--admin-key",
        ADMIN_KEY,
        "--epochs",
        "160",
        "--batch-epochs",
        "4",
        "--seed",
        "5",
        "--delay-fraction",
        "0.3",
        "--max-delay",
        "0.5",
        "--json",
        str(out),
    ]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "RMSE of the last fix received per epoch" in printed
    document = json.loads(out.read_text())
    assert list(document) == ["in order", "late", "late dropped"]
    rmse = {label: run["mean"]["position_rmse_m"] for label, run in document.items()}
    assert rmse["late"] == pytest.approx(rmse["in order"], rel=1e-9)
    assert rmse["late dropped"] > rmse["in order"]
    assert all(run["vehicles"][0]["error"] is None for run in document.values())


def test_a_vehicle_over_its_request_rate_waits_and_sends_again(tmp_path) -> None:
    """One-epoch batches sent as fast as answered exceed a low per-session request rate: every 429 is
    waited out (Retry-After) and the same batch sent again, so the run completes with every epoch fixed
    once and in order, and the waits are counted."""
    environment = clean_environment(
        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
        EDGEPOS_ADMIN_KEY_FILE=str(tmp_path / "admin.key"),
        EDGEPOS_LOG_LEVEL="warning",
        EDGEPOS_RATE_LIMIT_PER_S="20",
        EDGEPOS_RATE_LIMIT_BURST="10",
    )
    with running(serve_command(1), environment, tmp_path / "server.log", ready_timeout_s=300.0) as url:
        result = asyncio.run(run_simulation(url, admin_key=ADMIN_KEY, seed=2, batch_epochs=1, epochs=80))
    (vehicle,) = result.vehicles
    assert vehicle.error is None
    assert vehicle.rate_limited > 0
    assert [fix.t for fix in vehicle.fixes] == sorted({fix.t for fix in vehicle.fixes})
    assert len(vehicle.fixes) == 80
