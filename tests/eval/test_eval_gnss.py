"""``edgepos eval gnss`` in-process on one short run with few particles: JSON shape, sane errors, the
batching, argument errors and plots."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
from edgepos.core.observations import PseudorangeObservation, RissObservation
from edgepos.eval import commands, gnss_montecarlo
from edgepos.sim.gnss_scenario import urban_scenario
from edgepos.sim.gnss_sensors import simulate

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_eval(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="edgepos eval")
    commands.configure(parser)
    return commands.run(parser.parse_args(list(argv)))


@pytest.fixture(scope="module")
def urban_document(tmp_path_factory: pytest.TempPathFactory) -> dict:
    directory = tmp_path_factory.mktemp("gnss")
    path = directory / "out.json"
    code = run_eval(
        "gnss",
        "--runs",
        "1",
        "--short",
        "--particles",
        "20",
        "--workers",
        "1",
        "--seed",
        "3",
        "--json",
        str(path),
    )
    assert code == 0
    return json.loads(path.read_text())


def test_json_shape(urban_document: dict) -> None:
    assert urban_document["scenario"] == "urban-nanjing-short"
    assert urban_document["runs"] == 1 and urban_document["seed"] == 3 and urban_document["particles"] == 20
    assert set(urban_document["algorithms"]) == {
        "PF",
        "UPF",
        "UPF+fuzzy",
        "UKF",
        "UKF-equal",
        "UPF-default",
        "WLS",
    }
    for name, figures in urban_document["algorithms"].items():
        for key in ("horizontal_rms_m", "horizontal_max_m", "epoch_ms"):
            assert isinstance(figures[key], float) and math.isfinite(figures[key]), (name, key)
        assert 0.0 < figures["horizontal_rms_m"] <= figures["horizontal_max_m"] < 500.0
        assert figures["epoch_ms"] > 0.0
        assert figures["epochs_without_fix"] == 0 and figures["failed_batches"] == 0
        expected = None if name == "WLS" else 1 if name.startswith("UKF") else 20
        assert figures["particles"] == expected
    assert urban_document["algorithms"]["PF"]["paper"] == {
        "horizontal_rms_m": 4.34,
        "horizontal_max_m": 12.32,
    }
    assert urban_document["algorithms"]["UPF+fuzzy"]["paper"] == {
        "horizontal_rms_m": 3.39,
        "horizontal_max_m": 8.69,
    }
    assert urban_document["satellites_per_epoch"]["nlos"] > 0.0


def test_open_sky_ukf_is_metre_level(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "sky.json"
    code = run_eval(
        "gnss",
        "--runs",
        "1",
        "--short",
        "--scenario",
        "open-sky",
        "--algorithms",
        "ukf",
        "--workers",
        "1",
        "--json",
        str(path),
        "--plots",
        str(tmp_path / "plots"),
    )
    assert code == 0
    document = json.loads(path.read_text())
    assert list(document["algorithms"]) == ["UKF"]
    assert document["algorithms"]["UKF"]["horizontal_rms_m"] < 3.0
    for name in ("gnss_horizontal_error.png", "gnss_tracks.png"):
        assert (tmp_path / "plots" / name).read_bytes()[:8] == PNG_MAGIC
    assert "UKF" in capsys.readouterr().out


def test_batches_are_one_per_gnss_epoch() -> None:
    scenario = urban_scenario(short=True)
    run = simulate(scenario, np.random.default_rng(0))
    batches = gnss_montecarlo.batches(run, scenario.gnss_every)
    assert len(batches) == run.gnss_tow.size
    for k, batch in enumerate(batches):
        pseudoranges = [o for o in batch if isinstance(o, PseudorangeObservation)]
        assert pseudoranges and {o.t for o in pseudoranges} == {float(run.gnss_tow[k])}
        assert all(o.sat_position is not None and o.sat_clock is not None for o in pseudoranges)
        riss = [o for o in batch if isinstance(o, RissObservation)]
        assert len(riss) == (1 if k == 0 else scenario.gnss_every)
        assert riss[-1].t == run.gnss_tow[k]
    flattened = [o for batch in batches for o in batch]
    assert flattened == run.observations


@pytest.mark.parametrize(
    "argv",
    [
        ("gnss", "--algorithms", "nope"),
        ("gnss", "--particles", "5"),
        ("gnss", "--scenario", "moon"),
        ("gnss", "--option", "spread_fraction=1.5"),
        ("gnss", "--option", "no_such_option=1"),
        ("gnss", "--option", "spread_fraction"),
    ],
)
def test_bad_arguments(argv: tuple[str, ...], capsys: pytest.CaptureFixture[str]) -> None:
    try:
        code = run_eval(*argv, "--json", "/nonexistent-dir/x.json")
    except SystemExit as exc:  # argparse rejects choices and types itself
        code = exc.code
    assert code == 2
    assert capsys.readouterr().err


def test_option_overrides_reach_the_pipeline(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--option sets a pipeline option for every filter: the UPF with all of the uncertainty in its particles
    (spread_fraction 1) gives other fixes than with the default, and the JSON and report record it."""
    figures = {}
    for extra in ((), ("--option", "spread_fraction=1")):
        path = tmp_path / f"upf{len(extra)}.json"
        code = run_eval(
            "gnss",
            "--runs",
            "1",
            "--short",
            "--particles",
            "20",
            "--workers",
            "1",
            "--algorithms",
            "UPF+fuzzy",
            "--json",
            str(path),
            *extra,
        )
        assert code == 0
        document = json.loads(path.read_text())
        figures[len(extra)] = document["algorithms"]["UPF+fuzzy"]["horizontal_rms_m"]
        assert document["option_overrides"] == ({"spread_fraction": 1} if extra else {})
    assert figures[0] != figures[2]
    assert "options spread_fraction=1" in capsys.readouterr().out
