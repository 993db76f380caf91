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
    ("filter_name", "label"), [("upf", "upf (50 particles, fitted noise)"), ("ukf", "ukf (fitted noise)")]
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


def test_base_station_corrections_in_the_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--base`` (position from the header) and the same position given with ``--base-position`` give the
    same figures; the JSON names the station's position and its number of corrections."""
    base = str(DATA / "base-0-5min.rnx")
    documents = []
    for extra in ((), ("--base-position", "4777633.952592235,203108.98744838778,4206595.200050365")):
        path = tmp_path / f"base{len(extra)}.json"
        code = run_eval(
            "gnss-rinex",
            *FILES,
            "--filter",
            "ukf",
            "--max-epochs",
            "20",
            "--base",
            base,
            *extra,
            "--json",
            str(path),
        )
        assert code == 0
        documents.append(json.loads(path.read_text()))
    first, second = documents
    assert first["base"]["corrections"] > 3000
    assert first["base"]["position_ecef_m"] == pytest.approx(second["base"]["position_ecef_m"], abs=1e-6)
    assert first["horizontal_rms_m"] == pytest.approx(second["horizontal_rms_m"], abs=1e-6)
    assert "+ base" in capsys.readouterr().out


@pytest.mark.parametrize("position", ["1,2", "a,b,c", "0,0,0", "nan,0,0"])
def test_bad_base_position_is_refused_naming_the_argument(
    position: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        run_eval("gnss-rinex", *FILES, "--base", str(DATA / "base-0-5min.rnx"), "--base-position", position)
    assert exit_info.value.code == 2
    assert "--base-position" in capsys.readouterr().err


def test_base_file_without_a_position_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A base file whose header has no APPROX POSITION XYZ (and no --base-position) is refused by name."""
    lines = (DATA / "base-0-5min.rnx").read_text().splitlines(keepends=True)[:200]
    stripped = tmp_path / "base.rnx"
    stripped.write_text("".join(line for line in lines if "APPROX POSITION XYZ" not in line))
    assert run_eval("gnss-rinex", *FILES, "--max-epochs", "2", "--base", str(stripped)) == 2
    assert "APPROX POSITION XYZ" in capsys.readouterr().err
    assert run_eval("gnss-rinex", *FILES, "--max-epochs", "2", "--base", str(tmp_path / "none.rnx")) == 2
    # A position without a station would be ignored: refused instead.
    assert (
        run_eval("gnss-rinex", *FILES, "--max-epochs", "2", "--base-position", "4777633,203108,4206595") == 2
    )
    assert "--base-position needs --base" in capsys.readouterr().err
    assert run_eval("gnss-rinex", *FILES, "--max-epochs", "2", "--max-correction-age", "60") == 2
    assert "--max-correction-age needs --base" in capsys.readouterr().err
    assert (
        run_eval(
            "gnss-rinex",
            *FILES,
            "--max-epochs",
            "2",
            "--base",
            str(DATA / "base-0-5min.rnx"),
            "--max-correction-age",
            "0",
        )
        == 2
    )
    assert "maximum correction age must be in [1, 600] s" in capsys.readouterr().err


@pytest.mark.parametrize(("flags", "sent"), [((), True), (("--no-carrier",), False)])
def test_the_receivers_carrier_phase_is_sent_unless_told_not_to(
    tmp_path: Path, flags: tuple[str, ...], sent: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    """The eval sends what the receiver recorded, as a vehicle client would: the phase too by default."""
    path = tmp_path / "rinex.json"
    arguments = ("gnss-rinex", *FILES, "--filter", "ukf", "--max-epochs", "5", "--json", str(path), *flags)
    assert run_eval(*arguments) == 0
    assert json.loads(path.read_text())["carrier_sent"] is sent
    assert ("+ carrier" in capsys.readouterr().out) is sent
