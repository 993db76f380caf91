"""``edgepos eval v2v|federated --scene correlated``: RMSE and consistency (mean NEES) of the
cooperative pipelines on the correlated-error scene of ``sim/correlated.py`` (issue 21, item 0).

Every vehicle has its own session of the pipeline, fed one epoch at a time in lockstep as a server
would be; after each step every vehicle's track is published with the service's own rule, and in
the next step the others range against it. Per method: the 2-D position RMSE and the mean NEES of
the position (error^T P^-1 error with the fix's 2x2 covariance; 2 when consistent), over every
vehicle and every epoch from WARMUP_S on that it sent a batch (the GPS-only methods
send one only with a fix), of the runs of seeds ``seed .. seed + runs - 1``. ``--option NAME=JSON`` sets
a pipeline option for every method (here and with ``--faults``; e.g. ``consistency_scale=true``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from edgepos.cli_output import prepare_output
from edgepos.eval.montecarlo import chunk_runs, run_chunks
from edgepos.eval.overrides import add_option_argument, parse_overrides
from edgepos.eval.progress import Progress
from edgepos.eval.tables import format_table, number
from edgepos.pipelines import tracks
from edgepos.pipelines.base import NeighbourTrack, Pipeline, StaticEnvironment
from edgepos.pipelines.v2v_coop import V2vCoopPipeline
from edgepos.pipelines.v2x_federated import V2xFederatedPipeline
from edgepos.sim.correlated import STEP, STEPS, VEHICLE_IDS, CorrelatedRun, ErrorModel, make_run

WARMUP_S = 5.0
"""Epochs before this are the filters' start from a fix with no velocity: left out of both figures."""

_ALL = {"gnss_fix", "gyro", "odometer", "v2v_range"}
#: Per evaluation: method label -> (pipeline, options, observation kinds fed).
METHODS: dict[str, dict[str, tuple[type[Pipeline], dict[str, Any], set[str]]]] = {
    "v2v": {
        "GPS": (V2vCoopPipeline, {"method": "gps"}, _ALL),
        "GPS/DR": (V2vCoopPipeline, {"method": "gps_dr"}, _ALL),
        "UKF": (V2vCoopPipeline, {"method": "ukf"}, _ALL),
        "augUKF": (V2vCoopPipeline, {"method": "aug_ukf"}, _ALL),
    },
    "federated": {
        "GPS": (V2xFederatedPipeline, {}, {"gnss_fix"}),
        "GPS/DR": (V2xFederatedPipeline, {}, {"gnss_fix", "gyro", "odometer"}),
        "GPS/DR/V2X": (V2xFederatedPipeline, {}, _ALL),
    },
}


@dataclass
class Sums:
    """Per method: squared errors, NEES and fixes counted, summed over vehicles and runs per epoch."""

    squared: dict[str, np.ndarray] = field(default_factory=dict)
    nees: dict[str, np.ndarray] = field(default_factory=dict)
    counts: dict[str, np.ndarray] = field(default_factory=dict)
    runs: int = 0

    def add(self, method: str, squared: np.ndarray, nees: np.ndarray, counts: np.ndarray) -> None:
        self.squared[method] = self.squared.get(method, 0.0) + squared
        self.nees[method] = self.nees.get(method, 0.0) + nees
        self.counts[method] = self.counts.get(method, 0) + counts


def combine(a: Sums, b: Sums) -> Sums:
    for method in b.squared:
        a.add(method, b.squared[method], b.nees[method], b.counts[method])
    a.runs += b.runs
    return a


class RunFailed(RuntimeError):
    """A run raised an estimation error: which seed and method."""


def run_method(
    run: CorrelatedRun, pipeline: Pipeline, options: dict[str, Any], kinds: set[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Squared 2-D errors, position NEES and the number of vehicles with a fix per epoch, summed over
    the vehicles (steps,) each. A vehicle whose epoch has nothing of ``kinds`` sends no batch then."""
    resolved = pipeline.resolve_options(options)
    states = {vid: pipeline.create(resolved, None) for vid in VEHICLE_IDS}
    published: dict[str, NeighbourTrack] = {}
    steps = len(run.times)
    squared, nees, counts = np.zeros(steps), np.zeros(steps), np.zeros(steps)
    for k in range(steps):
        snapshot = dict(published)
        fixes_now = {}
        for i, vid in enumerate(VEHICLE_IDS):
            batch = [obs for obs in run.observations[i][k] if obs.kind in kinds]
            if not batch:
                continue
            fixes, states[vid] = pipeline.process(
                states[vid], batch, StaticEnvironment(tracks=snapshot, vehicle_id=vid)
            )
            fix = fixes[-1]
            error = np.array([fix.x - run.positions[i, k, 0], fix.y - run.positions[i, k, 1]])
            squared[k] += float(error @ error)
            nees[k] += float(error @ np.linalg.solve(np.array(fix.position_cov), error))
            counts[k] += 1
            fixes_now[vid] = fixes
        for vid, fixes in fixes_now.items():
            track = tracks.publish(vid, published.get(vid), fixes)
            if track is not None:
                published[vid] = track
    return squared, nees, counts


_CONFIG: dict[str, Any] = {}


def _init(evaluation: str, seed: int, errors: ErrorModel, overrides: dict[str, Any]) -> None:
    _CONFIG.update(evaluation=evaluation, seed=seed, errors=errors, overrides=overrides)


def _work(chunk: range) -> Sums:
    sums = Sums()
    for r in chunk:
        seed = _CONFIG["seed"] + r
        run = make_run(seed, _CONFIG["errors"])
        for method, (cls, options, kinds) in METHODS[_CONFIG["evaluation"]].items():
            try:
                squared, nees, counts = run_method(run, cls(), {**options, **_CONFIG["overrides"]}, kinds)
            except Exception as error:  # an estimation error names its run
                raise RunFailed(f"seed {seed} {method}: {error}") from error
            sums.add(method, squared, nees, counts)
        sums.runs += 1
    return sums


def monte_carlo(
    evaluation: str,
    runs: int,
    seed: int,
    workers: int,
    errors: ErrorModel,
    progress: Progress | None = None,
    overrides: dict[str, Any] | None = None,
) -> Sums:
    config = (evaluation, seed, errors, overrides or {})
    return run_chunks(_work, combine, chunk_runs(runs), workers, _init, config, progress)


def summary(sums: Sums) -> dict[str, dict[str, float]]:
    """{method: {pos_rmse_m, mean_nees}} over vehicles, runs and epochs from WARMUP_S on."""
    first = round(WARMUP_S / STEP)
    out = {}
    for method in sums.squared:
        count = float(sums.counts[method][first:].sum())
        out[method] = {
            "pos_rmse_m": math.sqrt(float(sums.squared[method][first:].sum()) / count),
            "mean_nees": float(sums.nees[method][first:].sum()) / count,
            "fixes": int(count),
        }
    return out


def report(
    results: dict[str, dict[str, float]], evaluation: str, runs: int, seed: int, errors: ErrorModel
) -> str:
    pipeline = METHODS[evaluation][next(iter(METHODS[evaluation]))][0].name
    lines = [
        (
            f"{pipeline} on the correlated-error scene: seeds {seed}-{seed + runs - 1}, {len(VEHICLE_IDS)} vehicles, "
            f"{STEPS} epochs of {STEP:g} s, fixes every {errors.fix_interval:g} s"
        ),
        (
            f"fix error per axis: common GM {errors.common_std:g} m / {errors.common_tau:g} s + own GM "
            f"{errors.vehicle_std:g} m / {errors.vehicle_tau:g} s + white {errors.white_std:g} m; "
            f"epochs from {WARMUP_S:g} s; NEES is 2 when consistent (2 dof)"
        ),
        "",
    ]
    rows = [
        [
            m,
            number(r["pos_rmse_m"], 2),
            number(r["mean_nees"], 2),
            "yes" if 1.0 <= r["mean_nees"] <= 4.0 else "NO",
        ]
        for m, r in results.items()
    ]
    lines.append(format_table(["method", "RMSE m", "mean NEES", "in 1-4"], rows, [False, True, True, False]))
    return "\n".join(lines)


def configure(parser: argparse.ArgumentParser) -> None:
    """The scene switch and the correlated scene's error options."""
    defaults = ErrorModel()
    parser.add_argument(
        "--scene",
        choices=("paper", "correlated"),
        default="paper",
        help="paper: the paper's scenarios and table; correlated: four vehicles on an S-curved road with "
        "time-correlated GNSS errors partly common to all, RMSE and mean NEES per method (seeds SEED.."
        "SEED+RUNS-1)",
    )
    for flag, attr, text in (
        ("--common-tau", "common_tau", "time constant (s) of the error common to all vehicles"),
        ("--common-std", "common_std", "1-sigma per axis (m) of the common error"),
        ("--vehicle-tau", "vehicle_tau", "time constant (s) of each vehicle's own correlated error"),
        ("--vehicle-std", "vehicle_std", "1-sigma per axis (m) of each vehicle's own correlated error"),
        ("--white-std", "white_std", "1-sigma per axis (m) of the white part of the fix error"),
        ("--fix-interval", "fix_interval", "seconds between GNSS fixes"),
    ):
        parser.add_argument(
            flag,
            dest=attr,
            type=_positive_float,
            default=getattr(defaults, attr),
            help=f"correlated scene: {text} (default {getattr(defaults, attr):g})",
        )
    add_option_argument(parser, "consistency_scale=true (with --scene correlated or --faults)")


def checked_overrides(args: argparse.Namespace, evaluation: str) -> dict[str, Any]:
    """The ``--option`` overrides, checked against the evaluation's pipeline; ValueError names a bad one
    (malformed, or refused by the pipeline)."""
    overrides = parse_overrides(args.option)
    pipeline = METHODS[evaluation][next(iter(METHODS[evaluation]))][0]
    pipeline().resolve_options(overrides)  # PipelineInputError is a ValueError naming the option
    return overrides


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value <= 0.0:
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def errors_from(args: argparse.Namespace) -> ErrorModel:
    """The correlated scene's error model from its flags."""
    return ErrorModel(
        args.common_tau,
        args.common_std,
        args.vehicle_tau,
        args.vehicle_std,
        args.white_std,
        args.fix_interval,
    )


def run(args: argparse.Namespace, evaluation: str, prog: str) -> int:
    """The correlated scene's command: table on stdout, ``{"scene": ..., "methods": ...}`` to --json."""
    try:
        overrides = checked_overrides(args, evaluation)
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if args.json is not None and (problem := prepare_output(args.json)) is not None:
        print(f"{prog}: error: --json: {problem}", file=sys.stderr)
        return 2
    errors = errors_from(args)
    progress = Progress(args.runs, label="runs")
    try:
        sums = monte_carlo(evaluation, args.runs, args.seed, args.workers, errors, progress, overrides)
    except RunFailed as exc:
        print(f"\n{prog}: error: {exc}", file=sys.stderr)
        return 1
    progress.finish()
    results = summary(sums)
    print(report(results, evaluation, args.runs, args.seed, errors))
    if args.json is not None:
        scene = {"name": "correlated", "seeds": [args.seed, args.seed + args.runs - 1], **vars(errors)}
        document = {"scene": scene, "option_overrides": overrides, "methods": results}
        try:
            Path(args.json).write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
        except OSError as exc:
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return 1
        print(f"\nwrote {args.json}")
    return 0
