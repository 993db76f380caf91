"""The capacity budget's arithmetic (bench/capacity_budget.py, ``wrk_load.py --budget``): the CPU an epoch
at a ratio of the floor, the parts every epoch costs, and what is left, from wrk results and the
compiled run's timing (stubbed here, so no filter runs)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from typing import Any

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


def _budget_module(monkeypatch: pytest.MonkeyPatch) -> Any:
    monkeypatch.syspath_prepend(str(BENCH))
    for name in ("capacity_budget", "run_call_cost"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    module = importlib.import_module("capacity_budget")
    timing = {"epochs": 20, "call, whole run": 400.0, "process": 720.0}
    monkeypatch.setattr(module.run_call_cost, "measure", lambda integrity, repeats: timing)
    return module


def test_the_budget_at_a_ratio_of_the_floor(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
):
    module = _budget_module(monkeypatch)
    floor = [
        {"epochs_per_s": 40_000.0, "server_cpu_us_per_epoch": 35.0, "wrk_cpu_us_per_epoch": 5.0},
        {"epochs_per_s": 50_000.0, "server_cpu_us_per_epoch": 37.0, "wrk_cpu_us_per_epoch": 6.0},
        {"epochs_per_s": 60_000.0, "server_cpu_us_per_epoch": 39.0, "wrk_cpu_us_per_epoch": 7.0},
    ]
    service = [
        {"server_cpu_us_per_epoch": 130.0, "wrk_cpu_us_per_epoch": 9.0, "redis_cpu_us_per_epoch": 20.0},
        {"server_cpu_us_per_epoch": 140.0, "wrk_cpu_us_per_epoch": 8.0, "redis_cpu_us_per_epoch": 18.0},
    ]
    figures = module.print_budget(0.5, floor, {"service": service}, 2)
    # 0.5 of the median floor, 50,000 epochs/s: 25,000 epochs/s on 2 cores, 80 us an epoch
    assert figures["budget_us"] == pytest.approx(80.0)
    assert figures["compiled_us"] == pytest.approx(20.0) and figures["pipeline_us"] == pytest.approx(36.0)
    assert figures["fixed_us"] == pytest.approx(37.0 + 6.0 + 20.0)
    assert figures["left_us"] == pytest.approx(80.0 - 63.0)
    assert figures["service us"] == pytest.approx(135.0 + 8.5 + 19.0)  # medians of each part
    printed = capsys.readouterr().out
    assert "left for everything else: 17.0 us an epoch, 340 us a 20-epoch batch" in printed
    assert "99.5 beyond the fixed parts" in printed


def test_nothing_left_is_said_so(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]):
    module = _budget_module(monkeypatch)
    floor = [{"epochs_per_s": 50_000.0, "server_cpu_us_per_epoch": 37.0, "wrk_cpu_us_per_epoch": 6.0}]
    figures = module.print_budget(0.9, floor, {"service": [{"server_cpu_us_per_epoch": 100.0}]}, 2)
    assert figures["left_us"] < 0
    assert "nothing is left beyond the fixed parts" in capsys.readouterr().out
