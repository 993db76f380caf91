"""``edgepos eval v2v``: Monte Carlo of the V2V cooperative-positioning paper's sec. 4 beside its Table 2.

Every vehicle of a run has its own ``v2v_coop`` session with the method under test, fed one epoch
at a time as a server would be. After each step every vehicle's track is published with the
service's own rule (``tracks.publish``), and in the next step its neighbours range against it:
the paper's "transmit the k-1 estimates" (Fig. 3). Position RMSE is over every vehicle and every
epoch after the first of every run (2-D error), as the paper's mean-RMSE over its four vehicles.
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
from edgepos.pipelines.v2v_coop import V2vCoopPipeline
from edgepos.sim.v2v import PAPER_OPTIONS, SCENARIOS, STEP, STEPS, VEHICLE_IDS, V2vRun, make_run

PROG = "edgepos eval v2v"
#: Table 2's methods and the pipeline's ``method`` option for each.
METHODS = {"GPS": "gps", "GPS/DR": "gps_dr", "UKF": "ukf", "augUKF": "aug_ukf"}
#: The paper's mean RMSE (m), sec. 4.1 text and Table 2.
PAPER = {
    "straight": {"GPS": 4.99, "GPS/DR": 3.40, "UKF": 2.37, "augUKF": 1.97},
    "ring": {"GPS": 5.04, "GPS/DR": 3.60, "UKF": 2.92, "augUKF": 2.35},
}
#: Table 2's improvement rates (eq. 31) of the augmented UKF over each other method, %.
PAPER_RATES = {
    ("straight", "GPS"): 60,
    ("straight", "GPS/DR"): 42,
    ("straight", "UKF"): 17,
    ("ring", "GPS"): 53,
    ("ring", "GPS/DR"): 35,
    ("ring", "UKF"): 20,
}


class RunFailed(RuntimeError):
    """A run raised an estimation error: which scenario, run and method."""


def run_method(run: V2vRun, method: str) -> tuple[np.ndarray, float, int]:
    """Squared 2-D errors per step summed over the vehicles (steps,), seconds in the pipelines and
    epochs processed, for one Table 2 ``method`` on one run."""
    pipeline = V2vCoopPipeline()
    # The paper's receiver has white errors and its vehicles take one another's estimates as independent.
    options = pipeline.resolve_options({"method": METHODS[method], **PAPER_OPTIONS})
    states = {vid: pipeline.create(options, None) for vid in VEHICLE_IDS}
    published: dict[str, NeighbourTrack] = {}
    steps = len(run.times)
    squared = np.zeros(steps)
    elapsed = 0.0
    for k in range(steps):
        snapshot = dict(published)  # every vehicle ranges against the others' estimates of step k-1
        fixes_now = {}
        for i, vid in enumerate(VEHICLE_IDS):
            environment = StaticEnvironment(tracks=snapshot, vehicle_id=vid)
            started = time.perf_counter()
            fixes, states[vid] = pipeline.process(states[vid], run.observations[i][k], environment)
            elapsed += time.perf_counter() - started
            fix = fixes[-1]
            squared[k] += (fix.x - run.positions[i, k, 0]) ** 2 + (fix.y - run.positions[i, k, 1]) ** 2
            fixes_now[vid] = fixes
        for vid, fixes in fixes_now.items():
            track = tracks.publish(vid, published.get(vid), fixes)
            if track is not None:
                published[vid] = track
    return squared, elapsed, steps * len(VEHICLE_IDS)


_SEED = 1


def _init(seed: int) -> None:
    global _SEED
    _SEED = seed


def _work(chunk: range) -> Totals:
    totals = Totals()
    for scenario in SCENARIOS:
        for r in chunk:
            run = make_run(_SEED, r, scenario)
            for method in METHODS:
                key = (scenario, method)
                try:
                    squared, seconds, epochs = run_method(run, method)
                except Exception as error:  # an estimation error names its run
                    raise RunFailed(f"{scenario} run {r} {method}: {error}") from error
                totals.add(key, squared, seconds, epochs)
    return totals


def monte_carlo(runs: int, seed: int, workers: int, progress: Progress | None = None) -> Totals:
    return run_chunks(_work, combine, chunk_runs(runs), workers, _init, (seed,), progress)


def summary(totals: Totals, runs: int) -> dict[str, dict[str, dict[str, float]]]:
    """{scenario: {method: {pos_rmse_m, step_us}}}: RMSE over vehicles and epochs 1.. of every run."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for (scenario, method), squared in totals.squared.items():
        rmse = math.sqrt(float(squared[1:].sum()) / (runs * len(VEHICLE_IDS) * (len(squared) - 1)))
        step_us = totals.seconds[(scenario, method)] / totals.epochs[(scenario, method)] * 1e6
        out.setdefault(scenario, {})[method] = {"pos_rmse_m": rmse, "step_us": step_us}
    return out


def rate(better: float, worse: float) -> float:
    """Eq. 31: improvement of ``better`` over ``worse`` in percent."""
    return (1.0 - better / worse) * 100.0


def report(results: dict[str, dict[str, dict[str, float]]], runs: int, seed: int) -> str:
    lines = [
        (
            f"V2V cooperative positioning (Qiao & Qu 2021, sec. 4): {runs} runs, seed {seed}, "
            f"{len(VEHICLE_IDS)} vehicles, {STEPS} epochs of {STEP:g} s"
        ),
        "",
    ]
    rows = []
    for method in METHODS:
        row = [method]
        for scenario in SCENARIOS:
            row += [number(results[scenario][method]["pos_rmse_m"], 2), number(PAPER[scenario][method], 2)]
        row.append(number(results["straight"][method]["step_us"], 0))
        rows.append(row)
    headers = ["method", "straight RMSE m", "paper", "ring RMSE m", "paper", "us/epoch"]
    lines.append(format_table(headers, rows, [False, True, True, True, True, True]))
    lines += ["", "Improvement of augUKF (eq. 31), ours vs paper:"]
    rate_rows = []
    for scenario in SCENARIOS:
        for base in ("GPS", "GPS/DR", "UKF"):
            ours = rate(results[scenario]["augUKF"]["pos_rmse_m"], results[scenario][base]["pos_rmse_m"])
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
    return "\n".join(lines)


def configure(parser: argparse.ArgumentParser) -> None:
    """``--scene`` (the paper's or the correlated-error one) and the correlated scene's options."""
    correlated.configure(parser)
    cooperative_integrity.configure(parser)


def curves(totals: Totals, runs: int) -> dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]:
    """Per scenario: times and each method's RMSE over time (over runs and vehicles)."""
    t = np.arange(STEPS) * STEP
    count = runs * len(VEHICLE_IDS)
    return {s: (t, {m: np.sqrt(totals.squared[(s, m)] / count) for m in METHODS}) for s in SCENARIOS}


def run(args: argparse.Namespace) -> int:
    if args.faults:
        return cooperative_integrity.run(args, "v2v", PROG)
    if args.scene == "correlated":
        return correlated.run(args, "v2v", PROG)
    if args.option:
        print(f"{PROG}: error: --option applies with --scene correlated or --faults", file=sys.stderr)
        return 2
    return run_scenario_command(args, PROG, monte_carlo, summary, report, curves, "v2v", RunFailed)
