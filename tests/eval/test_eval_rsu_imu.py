"""``edgepos eval rsu-imu`` run in-process on a short subset: JSON shape, plausible values, errors,
independence from the worker count, plots; plus the pure helpers (selection, chunking, tables)."""

from __future__ import annotations

import argparse
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from edgepos.eval import commands, montecarlo, rsu_imu_algorithms, rsu_imu_montecarlo, rsu_imu_report
from edgepos.eval.progress import Progress

SUBSET = "2IMM-CKF,CV-CKF/avg"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_eval(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="edgepos eval")
    commands.configure(parser)
    return commands.run(parser.parse_args(list(argv)))


@dataclass
class Outcome:
    code: int
    stdout: str
    document: dict
    plots: Path


@pytest.fixture(scope="module")
def one_worker(tmp_path_factory: pytest.TempPathFactory) -> Outcome:
    """Two runs of the subset on one worker, with --json and --plots (the expensive part, run once)."""
    directory = tmp_path_factory.mktemp("eval")
    json_path, plot_dir = directory / "out.json", directory / "plots"
    stdout = io.StringIO()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("sys.stdout", stdout)
        patch.setattr("sys.stderr", io.StringIO())
        code = run_eval(
            "rsu-imu",
            "--runs",
            "2",
            "--seed",
            "7",
            "--workers",
            "1",
            "--algorithms",
            SUBSET,
            "--json",
            str(json_path),
            "--plots",
            str(plot_dir),
        )
    return Outcome(code, stdout.getvalue(), json.loads(json_path.read_text()), plot_dir)


def test_json_has_exactly_the_documented_shape(one_worker: Outcome) -> None:
    assert one_worker.code == 0
    document = one_worker.document
    assert set(document) <= {"scenario", "runs", "seed", "algorithms", "notes"}
    assert (document["scenario"], document["runs"], document["seed"]) == ("rsu-imu-paper", 2, 7)
    assert list(document["algorithms"]) == ["CV-CKF/avg", "2IMM-CKF"]
    for entry in document["algorithms"].values():
        # the smoothed columns come by default (--smooth-lag 1.0); the late ones only with --delay-fraction;
        # the integrity figures always (docs/integrity.md)
        assert set(entry) == {
            "pos_rmse_m",
            "vel_rmse_mps",
            "step_us",
            "smooth_pos_rmse_m",
            "smooth_vel_rmse_mps",
            "integrity",
        }
        assert entry["smooth_pos_rmse_m"] < entry["pos_rmse_m"]
        integrity = entry.pop("integrity")
        assert integrity["epochs"] == 1600 and integrity["misleading"] == 0
        assert all(isinstance(value, float) for value in entry.values())


def test_values_are_plausible(one_worker: Outcome) -> None:
    for name, entry in one_worker.document["algorithms"].items():
        assert 0.02 < entry["pos_rmse_m"] < 1.0, name
        assert 0.05 < entry["vel_rmse_mps"] < 5.0, name
        assert entry["step_us"] > 0.0, name


def test_report_sets_paper_figures_beside_the_rows(one_worker: Outcome) -> None:
    lines = one_worker.stdout.splitlines()
    average_row = next(line for line in lines if line.startswith("CV-CKF/avg "))
    joint_row = next(line for line in lines if line.startswith("2IMM-CKF "))
    assert "0.2210" in average_row and "(0.2210)" not in average_row
    assert "(0.1675)" in joint_row and "(345.1)" in joint_row
    assert "not the benchmark figure" in one_worker.stdout


def test_plots_are_written(one_worker: Outcome) -> None:
    expected = {
        "position_rmse_imm_joint.png",
        "velocity_rmse_imm_joint.png",
        "model_probabilities_2imm_ckf_joint.png",
        "position_rmse_single_avg.png",
        "velocity_rmse_single_avg.png",
        "stanford_2imm_ckf.png",  # Stanford diagrams: error against protection level (docs/integrity.md)
        "stanford_cv_ckf_avg.png",
    }
    assert {path.name for path in one_worker.plots.iterdir()} == expected
    for name in expected:
        content = (one_worker.plots / name).read_bytes()
        assert content.startswith(PNG_MAGIC) and len(content) > 10_000, name


def test_results_do_not_depend_on_the_worker_count(one_worker: Outcome, tmp_path: Path, capsys) -> None:
    json_path = tmp_path / "two.json"
    code = run_eval(
        "rsu-imu",
        "--runs",
        "2",
        "--seed",
        "7",
        "--workers",
        "2",
        "--algorithms",
        SUBSET,
        "--json",
        str(json_path),
    )
    assert code == 0
    two = json.loads(json_path.read_text())["algorithms"]
    for name, entry in one_worker.document["algorithms"].items():
        assert two[name]["pos_rmse_m"] == entry["pos_rmse_m"], name
        assert two[name]["vel_rmse_mps"] == entry["vel_rmse_mps"], name


def test_unknown_algorithm_is_a_clear_error(capsys) -> None:
    code = run_eval("rsu-imu", "--runs", "1", "--workers", "1", "--algorithms", "2IMM-CKF,Kalman-9000")
    assert code == 2
    err = capsys.readouterr().err
    assert "'Kalman-9000'" in err and "2IMM-CKF/avg" in err  # names the culprit and the choices


def test_bad_run_count_is_rejected_by_the_parser(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        run_eval("rsu-imu", "--runs", "0")
    assert exit_info.value.code == 2
    assert "--runs" in capsys.readouterr().err


def test_an_option_override_changes_the_result_and_is_recorded(
    one_worker: Outcome, tmp_path: Path, capsys
) -> None:
    json_path = tmp_path / "sigma.json"
    override = '{"singer": {"sigma": 2.0}, "cv": {"q": 1.0}}'
    code = run_eval(
        "rsu-imu",
        "--runs",
        "2",
        "--seed",
        "7",
        "--workers",
        "1",
        "--algorithms",
        SUBSET,
        "--option",
        f"model_params={override}",
        "--json",
        str(json_path),
    )
    assert code == 0
    assert '"sigma": 2.0' in capsys.readouterr().out  # the report says the defaults were not used
    document = json.loads(json_path.read_text())
    assert document["option_overrides"] == {"model_params": json.loads(override)}
    for name, entry in document["algorithms"].items():  # both rows ran something else than the defaults
        assert entry["pos_rmse_m"] != one_worker.document["algorithms"][name]["pos_rmse_m"], name


@pytest.mark.parametrize(
    ("option", "says"),
    [
        ('filter="ekf"', "--algorithms"),
        ("priority=[]", "--algorithms"),
        ("gate_probability", "NAME=JSON"),
        ("gate_probability=0.9x", "must be JSON"),
        ("gate_probability=7", "gate_probability"),
        ('model_params={"singer": {"sigmaa": 2}}', "sigmaa"),
    ],
)
def test_a_bad_option_override_is_refused_before_any_run(option: str, says: str, capsys) -> None:
    assert run_eval("rsu-imu", "--runs", "1", "--workers", "1", "--option", option) == 2
    assert says in capsys.readouterr().err


def test_model_params_go_only_to_banks_with_that_model() -> None:
    chosen = rsu_imu_algorithms.select_algorithms("CV-CKF,Singer-CKF,2IMM-CKF")
    sigma = {"singer": {"sigma": 2}}
    changed = rsu_imu_algorithms.with_overrides(chosen, {"model_params": sigma, "max_rsus": 3})
    assert [a.options["model_params"] for a in changed] == [{}, sigma, sigma]
    assert all(a.options["max_rsus"] == 3 for a in changed)
    assert all("model_params" not in a.options and "max_rsus" not in a.options for a in chosen)  # not mutated


# -- pure helpers --------------------------------------------------------------------------------
def test_selection_is_case_insensitive_and_in_table_order() -> None:
    chosen = rsu_imu_algorithms.select_algorithms(" 2imm-ckf , cv-ckf/AVG,2IMM-CKF")
    assert [a.name for a in chosen] == ["CV-CKF/avg", "2IMM-CKF"]
    assert chosen[0].options["rsu_handling"] == "average" and chosen[1].options["rsu_handling"] == "joint"
    assert chosen[1].options["priority"] == ["ca", "at"]
    assert len(rsu_imu_algorithms.select_algorithms(None)) == 18


def test_chunks_cover_every_run_once_and_ignore_workers() -> None:
    for runs in (1, 2, 99, 200, 1001):
        chunks = montecarlo.chunk_runs(runs)
        assert [r for chunk in chunks for r in chunk] == list(range(runs))


def fake_result(name: str, pos: float, vel: float) -> rsu_imu_montecarlo.Result:
    algorithm = rsu_imu_algorithms.ALGORITHMS[name]
    return rsu_imu_montecarlo.Result(algorithm, np.full(5, pos), np.full(5, vel), None, 100.0)


def test_comparisons_match_the_papers_percentages() -> None:
    results = {
        name: fake_result(name, paper.pos_rmse_m, paper.vel_rmse_mps)
        for name, paper in rsu_imu_algorithms.PAPER.items()
    }
    table = rsu_imu_report.comparisons_table(results)
    assert table is not None
    row = next(line for line in table.splitlines() if line.startswith("2IMM-CKF vs IMM-CKF "))
    assert row.split()[-4:] == ["8.6", "5.9", "8.6", "5.9"]  # ours equal the paper's here
    row = next(line for line in table.splitlines() if line.startswith("IMM-CKF vs best single"))
    assert "Singer-CKF" in row and row.split()[-2] == "10.0"  # the paper's 10.0 % against Singer-CKF


def test_progress_off_a_terminal_writes_only_the_final_line() -> None:
    stream = io.StringIO()
    progress = Progress(3, stream=stream)
    progress.advance()
    progress.advance(2)
    progress.finish()
    assert stream.getvalue().count("\n") == 1 and "3/3" in stream.getvalue() and "\r" not in stream.getvalue()


def test_late_delivery_columns(tmp_path: Path) -> None:
    """--delay-fraction adds the last fix per epoch with late RSU data (equal to in order: replay is exact)
    and with those dropped (worse), beside the smoothed column."""
    json_path = tmp_path / "late.json"
    stdout = io.StringIO()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("sys.stdout", stdout)
        patch.setattr("sys.stderr", io.StringIO())
        code = run_eval(
            "rsu-imu",
            "--runs",
            "1",
            "--seed",
            "7",
            "--workers",
            "1",
            "--algorithms",
            "2IMM-CKF",
            "--delay-fraction",
            "0.3",
            "--max-delay",
            "0.5",
            "--batch-epochs",
            "5",
            "--json",
            str(json_path),
        )
    assert code == 0
    entry = json.loads(json_path.read_text())["algorithms"]["2IMM-CKF"]
    assert entry["late_pos_rmse_m"] == pytest.approx(entry["pos_rmse_m"], rel=1e-9)
    assert entry["drop_pos_rmse_m"] > entry["pos_rmse_m"] > entry["smooth_pos_rmse_m"]
    assert "late: last fix (m)" in stdout.getvalue() and "30% of the RSU measurements" in stdout.getvalue()


def test_bad_late_flags_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    for flags in (
        ("--delay-fraction", "1.5"),
        ("--delay-fraction", "0.3", "--max-delay", "0.01"),
        ("--smooth-lag", "-1"),
    ):
        assert run_eval("rsu-imu", "--runs", "1", "--algorithms", "2IMM-CKF", *flags) == 2
        assert "error" in capsys.readouterr().err


def test_faults_add_integrity_figures_and_bad_fault_flags_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    json_path = tmp_path / "faults.json"
    flags = ("rsu-imu", "--runs", "2", "--seed", "5", "--workers", "1", "--algorithms", "2IMM-CKF")
    assert run_eval(*flags, "--faults", "--fault-runs", "1", "--json", str(json_path)) == 0
    document = json.loads(json_path.read_text())
    figures = document["algorithms"]["2IMM-CKF"]["integrity"]
    assert figures["faulty_runs"] == 2 and figures["epochs"] == 1600
    assert figures["misleading"] == 0 and figures["hazardous"] == 0
    assert 0.9 < figures["availability"] <= 1.0
    assert document["faults"]["run_fraction"] == 1.0
    capsys.readouterr()
    for bad in (
        ("--fault-runs", "1.5"),
        ("--fault-bearing-offset", "4"),
        ("--fault-duration", "0"),
        ("--fault-range-bias", "0", "--fault-bearing-offset", "0"),
    ):
        assert run_eval(*flags, "--faults", *bad) == 2
        assert bad[0] in capsys.readouterr().err
