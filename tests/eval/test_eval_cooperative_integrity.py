"""``edgepos eval v2v|federated --faults``: the integrity block per scene and method, the faulty runs
counted, the fixes' RMSE and mean NEES, out-of-range fault flags and pipeline options refused with exit
2 naming them, and ``--option`` refused where it would be ignored."""

from __future__ import annotations

import json

import pytest
from edgepos.cli import main
from edgepos.eval.integrity import IntegrityTally


def test_v2v_faults_writes_the_integrity_block_per_scene_and_method(tmp_path, capsys):
    path = tmp_path / "out.json"
    code = main(
        ["eval", "v2v", "--faults", "--runs", "1", "--seed", "2", "--workers", "1", "--json", str(path)]
    )
    assert code == 0
    blocks = json.loads(path.read_text())["integrity"]
    assert set(blocks) == {f"{s} {m}" for s in ("straight", "ring") for m in ("UKF", "augUKF")}
    for block in blocks.values():
        # one run, every run faulty: the three vehicles ranging to the faulty one are its faulty runs
        assert block["epochs"] == 400 and block["faulty_runs"] == 3
        assert 0.0 <= block["availability"] <= 1.0 and block["alert_limit_m"] == 5.0
        assert block["median_protection_level_m"] > 0.0
        assert set(block) >= {
            "misleading",
            "hazardous",
            "detections",
            "detected_runs",
            "mean_detection_delay_s",
            "excluded_within_1s",
        }
        assert block["excluded_within_1s"] <= block["detected_within_1s"]
        assert 0.5 < block["pos_rmse_m"] < 5.0 and block["mean_nees"] > 0.0
    assert "Cooperative integrity" in capsys.readouterr().out


def test_an_option_changes_what_is_reported_not_the_fixes(tmp_path):
    blocks = {}
    for value in ("false", "true"):
        path = tmp_path / f"{value}.json"
        flags = ["--runs", "1", "--seed", "2", "--workers", "1", "--json", str(path)]
        code = main(["eval", "v2v", "--faults", *flags, "--option", f"consistency_scale={value}"])
        assert code == 0
        blocks[value] = json.loads(path.read_text())["integrity"]
    for key, before in blocks["false"].items():
        after = blocks["true"][key]
        assert after["pos_rmse_m"] == before["pos_rmse_m"]
        assert after["mean_nees"] <= before["mean_nees"]
        assert after["median_protection_level_m"] >= before["median_protection_level_m"]


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--faults", "--option", "consistency_time_constant_s=0.1"], "consistency_time_constant_s"),
        (["--faults", "--option", "consistency_scale"], "NAME=JSON"),
        (["--scene", "correlated", "--option", "no_such_option=1"], "no_such_option"),
        (["--option", "consistency_scale=true"], "--option applies"),
    ],
)
@pytest.mark.parametrize("evaluation", ["v2v", "federated"])
def test_bad_or_ignored_options_exit_2_naming_them(evaluation, flags, named, capsys):
    code = main(["eval", evaluation, "--runs", "1", "--workers", "1", *flags])
    assert code == 2
    assert named in capsys.readouterr().err


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--fault-runs", "1.5"], "--fault-runs"),
        (["--fault-offset", "-3"], "--fault-offset"),
        (["--fault-duration", "0"], "--fault-duration"),
    ],
)
@pytest.mark.parametrize("evaluation", ["v2v", "federated"])
def test_out_of_range_fault_flags_exit_2_naming_the_flag(evaluation, flags, named, capsys):
    code = main(["eval", evaluation, "--faults", "--runs", "1", *flags])
    assert code == 2
    assert named in capsys.readouterr().err


def test_a_scaled_tally_reads_its_median_in_metres():
    tally = IntegrityTally(scale=4.0)
    tally.diagram[0, 100] = 1.0  # bin 100 of 0-3 m in 2 cm steps, times 4: 8.00-8.08 m
    assert 8.0 <= tally.median_protection_level() <= 8.08
