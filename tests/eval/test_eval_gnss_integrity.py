"""The integrity block of the GNSS evaluations (issue 21): ``edgepos eval gnss-rinex`` on the real recording
(tests/data/gnss-rover, UKF, whole five minutes, with and without the base station) counts no misleading
epoch and reports availability and a Stanford diagram; ``edgepos eval gnss --faults`` injects a satellite
ramp that is detected in every run, and refuses out-of-range fault flags naming them."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest
from edgepos.eval import commands

DATA = Path(__file__).resolve().parents[1] / "data" / "gnss-rover"
FILES = (
    "--obs",
    str(DATA / "rover-0-5min.rnx"),
    "--nav",
    str(DATA / "broadcast-nav.rnx"),
    "--reference",
    str(DATA / "reference-0-5min.csv"),
)
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_eval(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="edgepos eval")
    commands.configure(parser)
    return commands.run(parser.parse_args(list(argv)))


@pytest.mark.parametrize("base", [False, True])
def test_the_recording_has_no_misleading_epoch(tmp_path: Path, capsys, base: bool) -> None:
    path = tmp_path / "out.json"
    extra = ("--base", str(DATA / "base-0-5min.rnx")) if base else ()
    code = run_eval(
        "gnss-rinex", *FILES, "--filter", "ukf", *extra, "--json", str(path), "--plots", str(tmp_path)
    )
    assert code == 0
    block = json.loads(path.read_text())["integrity"]
    assert block["epochs"] >= 280  # the reference's epochs with a fix
    assert block["misleading"] == 0 and block["hazardous"] == 0
    assert block["max_error_over_protection_level"] < 1.0
    assert 0.0 <= block["availability"] <= 1.0
    assert block["unavailable_rate"] < 0.01  # only the initialising fix
    assert block["mean_nees_inflated"] < block["mean_nees"]
    assert Path(block["stanford_plot"]).read_bytes()[:8] == PNG_MAGIC
    assert "integrity (alert limit 5 m)" in capsys.readouterr().out


def test_a_wider_alert_limit_makes_the_recording_available(tmp_path: Path) -> None:
    path = tmp_path / "out.json"
    code = run_eval(
        "gnss-rinex",
        *FILES,
        "--filter",
        "ukf",
        "--max-epochs",
        "60",
        "--option",
        "alert_limit_m=40",
        "--json",
        str(path),
    )
    assert code == 0
    block = json.loads(path.read_text())["integrity"]
    assert block["availability"] > 0.9 and block["misleading"] == 0


def test_a_simulated_satellite_ramp_is_detected_in_every_run(tmp_path: Path, capsys) -> None:
    path = tmp_path / "faults.json"
    argv = ("gnss", "--runs", "2", "--short", "--algorithms", "ukf", "--workers", "1", "--seed", "3")
    code = run_eval(*argv, "--faults", "--fault-rate", "2", "--fault-size", "40", "--json", str(path))
    assert code == 0
    document = json.loads(path.read_text())
    assert document["faults"] == {"ramp_mps": 2.0, "size_m": 40.0}
    block = document["algorithms"]["UKF"]["integrity"]
    assert block["faulty_runs"] == 2 and block["detected_runs"] == 2
    assert block["mean_detection_delay_s"] < 10.0
    assert block["misleading"] == 0
    assert block["median_protection_level_m"] is not None
    assert "UKF integrity" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--fault-rate", "0"), ("--fault-rate", "1000"), ("--fault-size", "-1"), ("--fault-size", "x")],
)
def test_out_of_range_fault_flags_exit_2_naming_the_flag(flag: str, value: str, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        run_eval("gnss", "--faults", flag, value)
    assert exit_.value.code == 2
    assert flag in capsys.readouterr().err
