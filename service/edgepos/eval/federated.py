"""``edgepos eval federated``: Monte Carlo of the V2X federated paper's sec. 3 beside its Table 1 and Fig. 5.

Every method is the ``v2x_federated`` pipeline fed one batch per epoch, as a server would be: GPS
with the GNSS fixes only, GPS/DR adding gyro and odometer, GPS/DR/V2X adding the V2V ranges, and the
same without feedback. Position RMSE is over every epoch after the first of every run (2-D error).
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from edgepos.eval import cooperative_integrity, correlated
from edgepos.eval.montecarlo import chunk_runs, run_chunks
from edgepos.eval.progress import Progress
from edgepos.eval.scenario_command import Totals, combine, run_scenario_command
from edgepos.eval.tables import format_table, number
from edgepos.pipelines import tracks
from edgepos.pipelines.base import NeighbourTrack, StaticEnvironment
from edgepos.pipelines.v2x_federated import V2xFederatedPipeline
from edgepos.sim.federated import PAPER_OPTIONS, SCENARIOS, STEPS, FederatedRun, make_run

PROG = "edgepos eval federated"
METHODS = ("GPS", "GPS/DR", "GPS/DR/V2X", "GPS/DR/V2X-nofeedback")
_KINDS = {
    "GPS": {"gnss_fix"},
    "GPS/DR": {"gnss_fix", "gyro", "odometer"},
    "GPS/DR/V2X": {"gnss_fix", "gyro", "odometer", "v2v_range"},
    "GPS/DR/V2X-nofeedback": {"gnss_fix", "gyro", "odometer", "v2v_range"},
}
#: The paper's Table 1, mean RMSE in metres.
PAPER = {
    "clean": {"GPS": 5.10, "GPS/DR": 3.50, "GPS/DR/V2X": 2.52},
    "multipath": {"GPS": 12.45, "GPS/DR": 7.02, "GPS/DR/V2X": 4.52},
}
PAPER_RATES = {
    ("clean", "GPS"): 51.0,
    ("clean", "GPS/DR"): 28.0,
    ("multipath", "GPS"): 64.0,
    ("multipath", "GPS/DR"): 36.0,
}


class RunFailed(RuntimeError):
    """A run raised an estimation error: which scenario, run and method."""


def assisting_tracks(run: FederatedRun) -> list[dict[str, NeighbourTrack]]:
    """What the server would publish of each assisting vehicle after each epoch: its own
    ``v2x_federated`` session fed its GNSS fixes, published with :func:`tracks.publish`."""
    pipeline = V2xFederatedPipeline()
    options = pipeline.resolve_options(PAPER_OPTIONS)
    states = {vid: pipeline.create(options, None) for vid in run.neighbour_ids}
    published: dict[str, NeighbourTrack | None] = dict.fromkeys(run.neighbour_ids)
    per_step = []
    for step_fixes in run.neighbour_fixes:
        for vid in run.neighbour_ids:
            fixes, states[vid] = pipeline.process(
                states[vid], [step_fixes[vid]], StaticEnvironment(vehicle_id=vid)
            )
            published[vid] = tracks.publish(vid, published[vid], fixes) or published[vid]
        per_step.append({vid: track for vid, track in published.items() if track is not None})
    return per_step


def run_method(
    run: FederatedRun, method: str, neighbours: list[dict[str, NeighbourTrack]] | None = None
) -> tuple[np.ndarray, float]:
    """Squared 2-D position errors per epoch (steps,) of one method on one run, and seconds spent
    in the target's pipeline. ``neighbours``: :func:`assisting_tracks` of the run (computed if None)."""
    if neighbours is None:
        neighbours = assisting_tracks(run)
    pipeline = V2xFederatedPipeline()
    options = pipeline.resolve_options({"feedback": method != "GPS/DR/V2X-nofeedback", **PAPER_OPTIONS})
    state = pipeline.create(options, None)
    kinds = _KINDS[method]
    squared = np.zeros(len(run.times))
    elapsed = 0.0
    for k, epoch in enumerate(run.observations):
        batch = [obs for obs in epoch if obs.kind in kinds]
        environment = StaticEnvironment(tracks=neighbours[k], vehicle_id="target")
        start = time.perf_counter()
        fixes, state = pipeline.process(state, batch, environment)
        elapsed += time.perf_counter() - start
        fix = fixes[-1]
        squared[k] = (fix.x - run.truth[k, 0]) ** 2 + (fix.y - run.truth[k, 3]) ** 2
    return squared, elapsed


_SEED = 1


def _init(seed: int) -> None:
    global _SEED
    _SEED = seed


def _work(chunk: range) -> Totals:
    totals = Totals()
    for scenario in SCENARIOS:
        for r in chunk:
            run = make_run(_SEED, r, scenario)
            neighbours = assisting_tracks(run)
            for method in METHODS:
                key = (scenario, method)
                try:
                    squared, seconds = run_method(run, method, neighbours)
                except Exception as error:  # an estimation error names its run
                    raise RunFailed(f"{scenario} run {r} {method}: {error}") from error
                totals.add(key, squared, seconds, len(squared))
    return totals


def monte_carlo(runs: int, seed: int, workers: int, progress: Progress | None = None) -> Totals:
    return run_chunks(_work, combine, chunk_runs(runs), workers, _init, (seed,), progress)


def summary(totals: Totals, runs: int) -> dict[str, dict[str, dict[str, float]]]:
    """{scenario: {method: {pos_rmse_m, step_us}}}: RMSE over epochs 1.. of every run."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for (scenario, method), squared in totals.squared.items():
        rmse = math.sqrt(float(squared[1:].sum()) / (runs * (len(squared) - 1)))
        step_us = totals.seconds[(scenario, method)] / totals.epochs[(scenario, method)] * 1e6
        out.setdefault(scenario, {})[method] = {"pos_rmse_m": rmse, "step_us": step_us}
    return out


def rate(better: float, worse: float) -> float:
    """Eq. 17: improvement of ``better`` over ``worse`` in percent."""
    return (1.0 - better / worse) * 100.0


def report(results: dict[str, dict[str, dict[str, float]]], runs: int, seed: int) -> str:
    lines = [
        f"V2X federated filter (Wang et al. 2019, sec. 3): {runs} runs, seed {seed}, {STEPS} epochs of 0.2 s",
        "",
    ]
    rows = []
    for method in METHODS:
        row = [method]
        for scenario in SCENARIOS:
            row += [
                number(results[scenario][method]["pos_rmse_m"], 2),
                number(PAPER[scenario].get(method), 2),
            ]
        row.append(number(results["clean"][method]["step_us"], 0))
        rows.append(row)
    headers = ["method", "clean RMSE m", "paper", "multipath RMSE m", "paper", "us/epoch"]
    lines.append(format_table(headers, rows, [False, True, True, True, True, True]))
    lines += ["", "Improvement of GPS/DR/V2X (eq. 17), ours vs paper:"]
    rate_rows = []
    for scenario in SCENARIOS:
        for base in ("GPS", "GPS/DR"):
            ours = rate(results[scenario]["GPS/DR/V2X"]["pos_rmse_m"], results[scenario][base]["pos_rmse_m"])
            paper = PAPER_RATES[(scenario, base)]
            rate_rows.append(
                [
                    scenario,
                    f"over {base}",
                    f"{ours:.1f}",
                    f"{paper:.0f}",
                    "yes" if ours >= paper - 5 else "NO",
                ]
            )
    lines.append(
        format_table(
            ["scenario", "", "ours %", "paper %", ">= paper-5"], rate_rows, [False, False, True, True, False]
        )
    )
    lines += ["", "Fig. 5, feedback on vs off (GPS/DR/V2X):"]
    for scenario in SCENARIOS:
        on = results[scenario]["GPS/DR/V2X"]["pos_rmse_m"]
        off = results[scenario]["GPS/DR/V2X-nofeedback"]["pos_rmse_m"]
        lines.append(
            f"  {scenario}: feedback {on:.2f} m, no feedback {off:.2f} m ({rate(on, off):.1f} % better with)"
        )
    return "\n".join(lines)


def configure(parser: argparse.ArgumentParser) -> None:
    """``--scene`` (the paper's or the correlated-error one) and the correlated scene's options."""
    correlated.configure(parser)
    cooperative_integrity.configure(parser)


def curves(totals: Totals, runs: int) -> dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]:
    """Per scenario: times and each method's RMSE over time."""
    t = np.arange(STEPS) * 0.2
    return {s: (t, {m: np.sqrt(totals.squared[(s, m)] / runs) for m in METHODS}) for s in SCENARIOS}


def run(args: argparse.Namespace) -> int:
    if args.faults:
        return cooperative_integrity.run(args, "federated", PROG)
    if args.scene == "correlated":
        return correlated.run(args, "federated", PROG)
    if args.option:
        print(f"{PROG}: error: --option applies with --scene correlated or --faults", file=sys.stderr)
        return 2
    return run_scenario_command(args, PROG, monte_carlo, summary, report, curves, "federated", RunFailed)
