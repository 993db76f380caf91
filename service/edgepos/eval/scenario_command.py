"""The command flow every scenario-table evaluation shares (``eval v2v``, ``eval federated``): check
the output paths, run the Monte Carlo with a progress line, print the table, write the JSON summary
and one RMSE-over-time figure per scenario."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from edgepos.cli_output import prepare_output
from edgepos.eval import plots
from edgepos.eval.progress import Progress

Summary = dict[str, dict[str, dict[str, float]]]


@dataclass
class Totals:
    """Sums over runs per (scenario, method): squared errors per epoch, seconds, epochs."""

    squared: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    seconds: dict[tuple[str, str], float] = field(default_factory=dict)
    epochs: dict[tuple[str, str], int] = field(default_factory=dict)

    def add(self, key: tuple[str, str], squared: np.ndarray, seconds: float, epochs: int) -> None:
        self.squared[key] = self.squared.get(key, 0.0) + squared
        self.seconds[key] = self.seconds.get(key, 0.0) + seconds
        self.epochs[key] = self.epochs.get(key, 0) + epochs


def combine(a: Totals, b: Totals) -> Totals:
    """``a`` with ``b``'s sums added (the Monte Carlo's reduction over worker chunks)."""
    for key in b.squared:
        a.add(key, b.squared[key], b.seconds[key], b.epochs[key])
    return a


def run_scenario_command(
    args: argparse.Namespace,
    prog: str,
    monte_carlo: Callable[[int, int, int, Progress], Any],
    summarise: Callable[[Any, int], Summary],
    report: Callable[[Summary, int, int], str],
    curves: Callable[[Any, int], Mapping[str, tuple[np.ndarray, dict[str, np.ndarray]]]],
    plot_prefix: str,
    failure: type[Exception],
) -> int:
    """``curves(totals, runs)``: per scenario, the times and each method's RMSE over time."""
    if args.json is not None and (problem := prepare_output(args.json)) is not None:
        print(f"{prog}: error: --json: {problem}", file=sys.stderr)
        return 2
    if args.plots is not None:
        try:
            plots.require_matplotlib()
        except plots.PlotsUnavailable as exc:
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return 2
    progress = Progress(args.runs, label="runs")
    try:
        totals = monte_carlo(args.runs, args.seed, args.workers, progress)
    except failure as exc:
        print(f"\n{prog}: error: {exc}", file=sys.stderr)
        return 1
    progress.finish()
    results = summarise(totals, args.runs)
    print(report(results, args.runs, args.seed))
    try:
        if args.json is not None:
            Path(args.json).write_text(json.dumps({"scenarios": results}, indent=2) + "\n", encoding="utf-8")
            print(f"\nwrote {args.json}")
        if args.plots is not None:
            directory = Path(args.plots)
            directory.mkdir(parents=True, exist_ok=True)
            for scenario, (times, series) in curves(totals, args.runs).items():
                path = plots.line_plot(
                    directory / f"{plot_prefix}_{scenario}.png",
                    times,
                    series,
                    f"Position RMSE, {scenario}",
                    "RMSE (m)",
                    plots.readable_ylim(series),
                )
                print(f"wrote {path}")
    except OSError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    return 0
