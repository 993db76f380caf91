"""--json FILE creates the directories it names (``--json results/run.json`` in a fresh checkout)."""

from __future__ import annotations

import json
from pathlib import Path

from edgepos.cli import main
from edgepos.cli_output import prepare_output, write_output


def test_prepare_output_creates_the_missing_parents(tmp_path: Path) -> None:
    path = tmp_path / "results" / "deep" / "run.json"
    assert prepare_output(path) is None
    assert path.parent.is_dir() and not path.exists()
    assert prepare_output(tmp_path / "figures" / "a", directory=True) is None
    assert (tmp_path / "figures" / "a").is_dir()


def test_prepare_output_reports_a_directory_it_cannot_create(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    problem = prepare_output(tmp_path / "file" / "sub" / "run.json")
    assert problem is not None and "cannot create the directory" in problem and "file" in problem


def test_write_output_creates_the_parents(tmp_path: Path) -> None:
    path = tmp_path / "new" / "out.json"
    write_output(path, '{"a": 1}\n')
    assert json.loads(path.read_text()) == {"a": 1}


def test_eval_json_into_a_directory_that_does_not_exist_yet(tmp_path: Path) -> None:
    path = tmp_path / "results" / "v2v" / "correlated.json"
    argv = ["eval", "v2v", "--scene", "correlated", "--runs", "1", "--workers", "1", "--json", str(path)]
    assert main(argv) == 0
    assert json.loads(path.read_text())["scene"]["name"] == "correlated"


def test_eval_json_under_a_file_is_refused_before_the_runs(tmp_path: Path, capsys) -> None:
    (tmp_path / "results").write_text("not a directory")
    path = tmp_path / "results" / "run.json"
    argv = ["eval", "v2v", "--scene", "correlated", "--runs", "1", "--workers", "1", "--json", str(path)]
    assert main(argv) == 2
    assert "--json: cannot create the directory" in capsys.readouterr().err
