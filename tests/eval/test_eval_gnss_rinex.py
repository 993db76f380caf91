"""``edgepos eval gnss-rinex`` on the first epochs of the real recording: the JSON the issue specifies,
a fix at every epoch beside the least-squares baseline, and refused arguments and files."""

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


def run_eval(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="edgepos eval")
    commands.configure(parser)
    return commands.run(parser.parse_args(list(argv)))


@pytest.mark.parametrize(
    ("filter_name", "label"), [("upf", "upf (50 particles, fuzzy)"), ("ukf", "ukf (fuzzy)")]
)
def test_json_has_the_figures_of_filter_and_baseline(
    tmp_path: Path, filter_name: str, label: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "rinex.json"
    code = run_eval(
        "gnss-rinex",
        *FILES,
        "--filter",
        filter_name,
        "--particles",
        "50",
        "--max-epochs",
        "30",
        "--json",
        str(path),
    )
    assert code == 0
    document = json.loads(path.read_text())
    for figures in (document, document["baseline"]):
        assert figures["epochs"] == 30
        assert figures["fixes"] == 30
        assert 0.0 < figures["horizontal_rms_m"] < 15.0
        assert 0.0 < figures["horizontal_p95_m"] < 30.0
    assert f"gnss_tight {label}" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra",
    [
        ("--option", "no_such_option=1"),
        ("--option", "spread_fraction=2"),
        ("--option", "pseudorange_std"),
    ],
)
def test_refused_options_exit_2_with_a_message(
    extra: tuple[str, ...], capsys: pytest.CaptureFixture[str]
) -> None:
    assert run_eval("gnss-rinex", *FILES, "--max-epochs", "2", *extra) == 2
    assert "error" in capsys.readouterr().err


@pytest.mark.parametrize("systems", ["GR", ""])
def test_constellations_it_cannot_use_are_refused_not_left_out(
    systems: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as refused:  # argparse's usage error: exit status 2 and the reason
        run_eval("gnss-rinex", *FILES, "--max-epochs", "2", "--systems", systems)
    assert refused.value.code == 2
    assert "constellations must be letters of GCE" in capsys.readouterr().err


def test_missing_or_malformed_files_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = ("--obs", str(tmp_path / "none.rnx"), *FILES[2:])
    assert run_eval("gnss-rinex", *missing, "--max-epochs", "2") == 2
    garbage = tmp_path / "garbage.rnx"
    garbage.write_text("not a navigation file\n")
    malformed = (*FILES[:2], "--nav", str(garbage), *FILES[4:])
    assert run_eval("gnss-rinex", *malformed, "--max-epochs", "2") == 2
    assert capsys.readouterr().err.count("error") == 2
