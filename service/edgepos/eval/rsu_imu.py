"""``edgepos eval rsu-imu``: Monte Carlo of the RSU + IMU paper's sec. 5 beside its Tables 2 and 4.

The algorithms are in :mod:`rsu_imu_algorithms`, the runs and RMSE (eqs. 39-40) in
:mod:`rsu_imu_montecarlo`, the table, comparisons, JSON and figures in :mod:`rsu_imu_report`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from pathlib import Path

from edgepos.cli_output import prepare_output
from edgepos.eval import plots
from edgepos.eval.overrides import add_option_argument, parse_overrides
from edgepos.eval.progress import Progress
from edgepos.eval.rsu_imu_algorithms import (
    ALGORITHMS,
    Algorithm,
    UnknownAlgorithm,
    select_algorithms,
    with_overrides,
)
from edgepos.eval.rsu_imu_late import LateSettings
from edgepos.eval.rsu_imu_montecarlo import PIPELINE, RunFailed, initial_state, monte_carlo, results
from edgepos.eval.rsu_imu_report import report, to_json, write_plots
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.delivery import add_delivery_arguments, delivery_from
from edgepos.sim.faults import add_fault_arguments, faults_from
from edgepos.sim.scenarios import rsu_imu_paper_scenario

PROG = "edgepos eval rsu-imu"


def configure(parser: argparse.ArgumentParser) -> None:
    """The options specific to this evaluation (the common ones come from commands.py)."""
    parser.add_argument(
        "--algorithms",
        metavar="NAME,NAME...",
        default=None,
        help=f"comma-separated subset to run (default: all): {', '.join(ALGORITHMS)}",
    )
    add_option_argument(parser, 'model_params=\'{"singer": {"sigma": 2}}\'')
    parser.add_argument(
        "--smooth-lag",
        metavar="S",
        type=float,
        default=1.0,
        help="also report the fixed-lag smoothed RMSE, each epoch smoothed with the data up to S seconds after "
        "it (default 1.0, the default lag window; 0: no smoothing column)",
    )
    add_delivery_arguments(
        parser,
        "also deliver the runs with a fraction F of the RSU measurements late (see --max-delay), and report "
        "the RMSE of the last fix received per epoch beside the in-order run and beside dropping them",
    )
    parser.add_argument(
        "--batch-epochs",
        metavar="B",
        type=int,
        default=1,
        help="with --delay-fraction, the vehicle sends a batch every B epochs (default 1: each epoch as it happens)",
    )
    add_fault_arguments(parser)


def _error(message: str) -> None:
    print(f"{PROG}: error: {message}", file=sys.stderr)


def _check_options(algorithms: list[Algorithm]) -> None:
    """Refuse bad --option values here, by name, rather than in a worker process mid-run."""
    pipeline = get_pipeline(PIPELINE)
    start = initial_state(rsu_imu_paper_scenario())
    for algorithm in algorithms:
        pipeline.create(pipeline.resolve_options(algorithm.options), start)


def _late_settings(args: argparse.Namespace) -> LateSettings:
    """The smoothing and late-delivery columns asked for; ValueError naming a bad flag."""
    if not args.smooth_lag >= 0.0:
        raise ValueError("--smooth-lag must be >= 0")
    if args.batch_epochs < 1:
        raise ValueError("--batch-epochs must be >= 1")
    return LateSettings(args.smooth_lag or None, delivery_from(args), args.batch_epochs)


def run(args: argparse.Namespace) -> int:
    """Run the evaluation and print the report on stdout: 0 on success, 2 on bad arguments, 1 on failure."""
    try:
        overrides = parse_overrides(args.option)
        algorithms = with_overrides(select_algorithms(args.algorithms), overrides)
        _check_options(algorithms)
        late = _late_settings(args)
        faults = faults_from(args)
        if args.plots is not None:
            plots.require_matplotlib()
    except (UnknownAlgorithm, plots.PlotsUnavailable, ValueError) as exc:
        _error(str(exc))
        return 2
    if args.json is not None and (problem := prepare_output(args.json)) is not None:
        _error(f"--json: {problem}")
        return 2
    workers = args.workers or os.cpu_count() or 1

    progress = Progress(args.runs, label="runs")
    try:
        totals = monte_carlo(algorithms, args.runs, args.seed, workers, progress, late, faults)
    except RunFailed as exc:
        print(file=sys.stderr)
        _error(str(exc))
        return 1
    progress.finish()

    scenario = rsu_imu_paper_scenario()
    results_by_name = results(algorithms, totals)
    print(report(results_by_name, args.runs, args.seed, workers, late))
    if faults is not None:
        print(
            f"\nfaults injected: in {faults.run_fraction:g} of runs one RSU's range +{faults.range_bias_m:g} m or bearing "
            f"+{faults.bearing_offset_rad:g} rad for {faults.duration_s:g} s"
        )
    if overrides:
        print(f"\noptions set on every algorithm (not the paper's defaults): {json.dumps(overrides)}")
    diverged = [name for name, r in results_by_name.items() if not math.isfinite(r.pos_mean + r.vel_mean)]
    if diverged:
        _error(f"non-finite RMSE for {', '.join(diverged)}; nothing written")
        return 1
    try:
        if args.json is not None:
            document = to_json(results_by_name, scenario, args.runs, args.seed, workers, late)
            if faults is not None:
                document["faults"] = dataclasses.asdict(faults)
            if overrides:
                document["option_overrides"] = overrides
            Path(args.json).write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
            print(f"\nwrote {args.json}")
        if args.plots is not None:
            for path in write_plots(results_by_name, scenario, Path(args.plots)):
                print(f"wrote {path}")
    except OSError as exc:
        _error(str(exc))
        return 1
    return 0
