"""``edgepos eval gnss``: the tightly coupled GNSS + RISS paper's comparison (Jiang & Chen 2018, Table 2)
on the simulated Nanjing street-canyon drive.

The runs and figures are in :mod:`gnss_montecarlo`; this module holds the options, the report beside
Table 2, the ``--json`` document and the figures; ``--faults`` injects a satellite ramp (eval/gnss_ramp.py)
and every pipeline algorithm's integrity counts are reported.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from edgepos.cli_output import prepare_output
from edgepos.eval import plots
from edgepos.eval.gnss_montecarlo import (
    ALGORITHMS,
    PIPELINE,
    WLS,
    Result,
    RunFailed,
    Totals,
    UnknownAlgorithm,
    build_scenario,
    monte_carlo,
    results,
    select_algorithms,
)
from edgepos.eval.gnss_ramp import RATE_BOUNDS, SIZE_BOUNDS, Ramp, bounded, summary
from edgepos.eval.overrides import add_option_argument, parse_overrides
from edgepos.eval.progress import Progress
from edgepos.eval.tables import format_table, number, percent_change
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.gnss_scenario import SCENARIOS

PROG = "edgepos eval gnss"
TARGET_IMPROVEMENT_PERCENT = 20.0
PAPER_IMPROVEMENT_PERCENT = 21.88


def _particles(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 10 <= value <= 5000:
        raise argparse.ArgumentTypeError(f"must be between 10 and 5000, got {value}")
    return value


def configure(parser: argparse.ArgumentParser) -> None:
    """The options specific to this evaluation (the common ones come from commands.py)."""
    parser.add_argument(
        "--particles", type=_particles, default=200, help="particles of PF and UPF (default 200)"
    )
    parser.add_argument(
        "--scenario",
        choices=sorted(SCENARIOS),
        default="urban",
        help="urban: street canyons with NLOS (default); open-sky: the same drive without buildings",
    )
    parser.add_argument("--short", action="store_true", help="a 70 s route instead of the 6.5 min drive")
    parser.add_argument(
        "--algorithms",
        metavar="NAME,NAME...",
        default=None,
        help=f"comma-separated subset (default: all): {', '.join(ALGORITHMS)}",
    )
    parser.add_argument(
        "--faults",
        action="store_true",
        help="inject a satellite ramp into every run (one GPS satellite, from 30 %% of the run; "
        "eval/gnss_ramp.py); the integrity counts are reported either way",
    )
    parser.add_argument(
        "--fault-rate",
        type=bounded("--fault-rate", *RATE_BOUNDS),
        default=1.0,
        metavar="M/S",
        help=f"with --faults: the ramp's rate (m/s, {RATE_BOUNDS[0]:g}..{RATE_BOUNDS[1]:g}; default 1)",
    )
    parser.add_argument(
        "--fault-size",
        type=bounded("--fault-size", *SIZE_BOUNDS),
        default=50.0,
        metavar="M",
        help=f"with --faults: the bias the ramp stops growing at (m, {SIZE_BOUNDS[0]:g}..{SIZE_BOUNDS[1]:g}; "
        "default 50)",
    )
    add_option_argument(parser, "spread_fraction=0.1")


def _error(message: str) -> None:
    print(f"{PROG}: error: {message}", file=sys.stderr)


def _particle_count(result: Result, particles: int) -> int | None:
    """Particles of a particle filter, 1 for the UKF, None for the least squares (no filter)."""
    if result.algorithm.name == WLS:
        return None
    return particles if result.algorithm.uses_particles else 1


def _particle_cell(result: Result, particles: int) -> str:
    count = _particle_count(result, particles)
    return "-" if count is None else str(count)


def integrity_blocks(totals: Totals, args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """Per pipeline algorithm, its integrity counts (eval/gnss_ramp.py) at its alert limit."""
    pipeline = get_pipeline(PIPELINE)
    overrides = parse_overrides(args.option)
    out = {}
    for name, sums in totals.sums.items():
        if sums.integrity is None:
            continue
        options = pipeline.resolve_options({**ALGORITHMS[name].options, **overrides})
        out[name] = summary(sums.integrity, options["alert_limit_m"])
    return out


def report(
    results_by_name: dict[str, Result], totals: Totals, args: argparse.Namespace, scenario: str
) -> str:
    headers = [
        "algorithm",
        "particles",
        "RMS (m)",
        "max (m)",
        "mean run max (m)",
        "no fix",
        "failed",
        "excluded",
        "epoch (ms)",
        "paper RMS (m)",
        "paper max (m)",
    ]
    rows = []
    for result in results_by_name.values():
        paper = result.algorithm.paper
        rows.append(
            [
                result.algorithm.name,
                _particle_cell(result, args.particles),
                number(result.rms_m, 2),
                number(result.max_m, 2),
                number(result.mean_run_max_m, 2),
                str(result.missing),
                str(len(result.failures)),
                f"{100.0 * result.excluded_share:.1f} %",
                number(result.epoch_ms, 1),
                "-" if paper is None else number(paper.rms_m, 2),
                "-" if paper is None else number(paper.max_m, 2),
            ]
        )
    lines = [
        f"{PROG}: scenario {scenario}, {args.runs} run(s), seed {args.seed}, {args.particles} particles"
        + (f", options {' '.join(args.option)}" if args.option else ""),
        (
            f"satellites tracked per epoch (mean): {totals.los / totals.runs:.1f} line of sight, "
            f"{totals.nlos / totals.runs:.1f} reflected only (NLOS)"
        ),
        "",
        format_table(headers, rows, right=[False] + [True] * 10),
    ]
    for name, block in integrity_blocks(totals, args).items():
        lines.append(
            f"{name} integrity (alert limit {block['alert_limit_m']:g} m): availability "
            f"{block['availability']:.3f}, misleading {block['misleading']}, hazardous {block['hazardous']} "
            f"of {block['epochs']} epochs; detections {block['detections']} (false {block['false_exclusions']}); "
            f"faulty runs detected {block['detected_runs']}/{block['faulty_runs']}; median PL "
            f"{number(block['median_protection_level_m'], 2)} m"
        )
    for result in results_by_name.values():
        if result.failures:
            lines.append(
                f"{result.algorithm.name}: {len(result.failures)} failed batch(es); first: "
                f"{result.failures[0]}"
            )
    if "PF" in results_by_name and "UPF+fuzzy" in results_by_name:
        pf, upf = results_by_name["PF"], results_by_name["UPF+fuzzy"]
        change = percent_change(pf.rms_m, upf.rms_m)
        verdict = "meets" if change >= TARGET_IMPROVEMENT_PERCENT else "does NOT meet"
        lines += [
            "",
            (
                f"UPF+fuzzy vs PF: RMS {number(change, 1)} % lower (paper {PAPER_IMPROVEMENT_PERCENT} %), "
                f"mean run max {number(percent_change(pf.mean_run_max_m, upf.mean_run_max_m), 1)} % lower "
                f"(paper 29.46 %); {verdict} the {TARGET_IMPROVEMENT_PERCENT:.0f} % target."
            ),
        ]
    lines += [
        "",
        (
            "RMS and max over every GNSS epoch of every run; 'mean run max' is one drive's maximum averaged "
            "over runs (the paper's max is from its single drive). 'no fix': GNSS epochs without a position. "
            "'failed': batches the pipeline raised on (skipped, state kept, as the service would; for WLS, "
            "epochs it could not solve). 'excluded': pseudoranges not used (mask, residual test). Epoch time: "
            "wall time of "
            f"pipeline.process per GNSS epoch inside the Monte Carlo ({args.workers} worker(s) on "
            f"{os.cpu_count() or 1} core(s)), not the benchmark figure."
        ),
    ]
    return "\n".join(lines)


def to_json(
    results_by_name: dict[str, Result], totals: Totals, args: argparse.Namespace, scenario: str
) -> dict[str, Any]:
    algorithms = {}
    for name, result in results_by_name.items():
        paper = result.algorithm.paper
        algorithms[name] = {
            "horizontal_rms_m": result.rms_m,
            "horizontal_max_m": result.max_m,
            "epoch_ms": result.epoch_ms,
            "mean_run_max_m": result.mean_run_max_m,
            "epochs_without_fix": result.missing,
            "failed_batches": len(result.failures),
            "failures": result.failures[:20],
            "excluded_share": result.excluded_share,
            "particles": _particle_count(result, args.particles),
            "options": result.algorithm.options,
            "paper": None
            if paper is None
            else {"horizontal_rms_m": paper.rms_m, "horizontal_max_m": paper.max_m},
        }
    for name, block in integrity_blocks(totals, args).items():
        algorithms[name]["integrity"] = block
    return {
        "faults": None if not args.faults else {"ramp_mps": args.fault_rate, "size_m": args.fault_size},
        "scenario": scenario,
        "runs": args.runs,
        "seed": args.seed,
        "particles": args.particles,
        "option_overrides": parse_overrides(args.option),
        "satellites_per_epoch": {"los": totals.los / totals.runs, "nlos": totals.nlos / totals.runs},
        "algorithms": algorithms,
    }


def write_plots(results_by_name: dict[str, Result], totals: Totals, directory: Path) -> list[Path]:
    """Horizontal RMS over runs against time (cf. Fig. 3) and run 0's tracks (cf. Fig. 2)."""
    first = next(iter(results_by_name.values()))
    t = np.arange(first.curve.size, dtype=float)
    curves = {name: np.nan_to_num(result.curve) for name, result in results_by_name.items()}
    written = [
        plots.line_plot(
            directory / "gnss_horizontal_error.png",
            t,
            curves,
            "Horizontal error, RMS over runs (cf. Fig. 3)",
            "horizontal error (m)",
            plots.readable_ylim(curves),
        )
    ]
    if totals.track is not None:
        pyplot = plots.require_matplotlib()
        figure, axes = pyplot.subplots(figsize=(8, 6), dpi=110)
        try:
            for name, track in totals.track.items():
                style = (
                    {"color": "black", "linestyle": "--", "linewidth": 1.4}
                    if name == "truth"
                    else {"linewidth": 1.0}
                )
                axes.plot(track[:, 0], track[:, 1], label=name, **style)
            axes.set_title("Run 0: tracks in the site frame (cf. Fig. 2)")
            axes.set_xlabel("east (m)")
            axes.set_ylabel("north (m)")
            axes.set_aspect("equal", adjustable="datalim")
            axes.grid(True, alpha=0.3)
            axes.legend(loc="best", fontsize="small")
            figure.tight_layout()
            path = directory / "gnss_tracks.png"
            figure.savefig(path)
            written.append(path)
        finally:
            pyplot.close(figure)
    return written


def run(args: argparse.Namespace) -> int:
    """Run the evaluation and print the report: 0 on success, 2 on bad arguments, 1 on failure."""
    try:
        algorithms = select_algorithms(args.algorithms)
        if args.plots is not None:
            plots.require_matplotlib()
    except (UnknownAlgorithm, plots.PlotsUnavailable) as exc:
        _error(str(exc))
        return 2
    try:
        overrides = parse_overrides(args.option)
        get_pipeline(PIPELINE).resolve_options(overrides)
    except ValueError as exc:  # a malformed --option, or one the pipeline refuses (PipelineInputError)
        _error(str(exc))
        return 2
    # the arguments are sound: only now create the directories of --json
    if args.json is not None and (problem := prepare_output(args.json)) is not None:
        _error(f"--json: {problem}")
        return 2
    workers = args.workers or os.cpu_count() or 1
    args.workers = workers
    scenario = build_scenario(args.scenario, args.short).name

    progress = Progress(args.runs, label="runs")
    try:
        totals = monte_carlo(
            algorithms,
            args.runs,
            args.seed,
            workers,
            args.scenario,
            args.short,
            args.particles,
            progress,
            overrides,
            Ramp(args.fault_rate, args.fault_size) if args.faults else None,
        )
    except RunFailed as exc:
        print(file=sys.stderr)
        _error(str(exc))
        return 1
    progress.finish()
    results_by_name = results(algorithms, totals)
    print(report(results_by_name, totals, args, scenario))
    if not all(math.isfinite(r.rms_m) for r in results_by_name.values()):
        _error("non-finite error figures; nothing written")
        return 1
    try:
        if args.json is not None:
            document = to_json(results_by_name, totals, args, scenario)
            Path(args.json).write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
            print(f"\nwrote {args.json}")
        if args.plots is not None:
            for path in write_plots(results_by_name, totals, Path(args.plots)):
                print(f"wrote {path}")
    except OSError as exc:
        _error(str(exc))
        return 1
    return 0
