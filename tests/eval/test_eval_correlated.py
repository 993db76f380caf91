"""Consistency under time-correlated GNSS errors (issue 21, item 0): on the correlated-error scene
(four vehicles, fix errors = common + own Gauss-Markov + white, ranges between every pair) every
method of v2v_coop and v2x_federated reports a covariance that matches its error (mean NEES of the
position in [1, 4], 2 dof), and the same filter taking the fixes as white does not."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from edgepos.cli import main
from edgepos.eval.correlated import METHODS, run_method
from edgepos.pipelines.v2v_coop import V2vCoopPipeline
from edgepos.pipelines.v2x_federated import V2xFederatedPipeline
from edgepos.sim.correlated import VEHICLE_IDS, ErrorModel, make_run

_SEEDS = (100, 101)  # outside both the seeds the defaults were checked on (0-9) and reported on (10-29)
_STEPS = 150  # 30 s each: 2 runs x 4 vehicles x 125 epochs past the 5 s start
_FIRST = 25


@pytest.fixture(scope="module")
def runs():
    return [make_run(seed, ErrorModel(), steps=_STEPS) for seed in _SEEDS]


def _figures(runs, pipeline, options, kinds) -> tuple[float, float]:
    squared = nees = count = 0.0
    for run in runs:
        s, n, c = run_method(run, pipeline, options, kinds)
        squared += float(s[_FIRST:].sum())
        nees += float(n[_FIRST:].sum())
        count += float(c[_FIRST:].sum())
    return math.sqrt(squared / count), nees / count


@pytest.mark.parametrize("evaluation, method", [(e, m) for e in ("v2v", "federated") for m in METHODS[e]])
def test_every_method_is_consistent_on_correlated_errors(runs, evaluation, method):
    cls, options, kinds = METHODS[evaluation][method]
    rmse, mean_nees = _figures(runs, cls(), options, kinds)
    assert 1.0 <= mean_nees <= 4.0, (rmse, mean_nees)
    assert rmse < 4.5, rmse  # the fixes themselves are 3.8 m off (2-D RMS)


@pytest.mark.parametrize(
    "pipeline, options",
    [
        (V2vCoopPipeline, {"method": "gps_dr", "gnss_bias_std": 0.0}),
        (V2xFederatedPipeline, {"gnss_bias_std": 0.0}),
    ],
)
def test_the_same_filter_taking_the_fixes_as_white_is_overconfident(runs, pipeline, options):
    """The check can fail: without the bias states the covariance is several times too small."""
    _, mean_nees = _figures(runs, pipeline(), options, {"gnss_fix", "gyro", "odometer"})
    assert mean_nees > 6.0, mean_nees


def test_the_scene_has_the_error_model_it_says(runs):
    errors = np.concatenate([run.fix_errors[~np.isnan(run.fix_errors)] for run in runs])
    model = ErrorModel()
    assert errors.std() == pytest.approx(model.total_std, rel=0.25)
    # Errors common to the vehicles: at one time, two vehicles' errors share the common part's variance
    # (4 of 7.25 m^2 per axis; about zero, as a filter sees them, not about their means over 30 s).
    fixes = np.concatenate([run.fix_errors[:, ::5, :] for run in runs], axis=1)
    pairs = [np.mean(fixes[i] * fixes[j]) for i in range(len(VEHICLE_IDS)) for j in range(i)]
    assert np.mean(pairs) / np.mean(fixes**2) > 0.2


def test_eval_command_writes_rmse_and_nees(tmp_path, capsys):
    path = tmp_path / "out.json"
    code = main(
        [
            "eval",
            "v2v",
            "--scene",
            "correlated",
            "--runs",
            "1",
            "--seed",
            "3",
            "--workers",
            "1",
            "--json",
            str(path),
        ]
    )
    assert code == 0
    report = json.loads(path.read_text())
    assert report["scene"]["name"] == "correlated" and report["scene"]["seeds"] == [3, 3]
    assert set(report["methods"]) == set(METHODS["v2v"])
    for figures in report["methods"].values():
        assert figures["pos_rmse_m"] > 0.0 and figures["mean_nees"] > 0.0
    assert "mean NEES" in capsys.readouterr().out
