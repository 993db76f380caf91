"""Benchmark: gnss_tight's time per epoch on its defaults against the settings before issue 16 items 4-5.

The real rover recording (tests/data/gnss-rover, GPS + BeiDou + Galileo with Doppler and carrier phase, about
20 pseudoranges per epoch), one-epoch batches straight into the pipeline (no HTTP). "before" is the defaults
with ``noise_model`` fuzzy, ``fault_probability`` 0 (no fault test over time) and ``zupt`` off. The two are
run interleaved, repetition by repetition, so that load on the machine hits both alike; prints the median
milliseconds per epoch of each repetition and of all.

    python bench/gnss_tight_options.py [--epochs 200] [--reps 3] [--filter upf] [--particles 200]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from edgepos.core.observations import PseudorangeObservation
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
from edgepos.pipelines.base import StaticEnvironment
from edgepos.pipelines.gnss_recording import epoch_pseudoranges
from edgepos.pipelines.gnss_tight import GnssTightPipeline

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "gnss-rover"
CONFIGS = {
    "defaults": {},
    "before": {"noise_model": "fuzzy", "fault_probability": 0.0, "zupt": False},
}


def load(epochs: int) -> tuple[list[list[PseudorangeObservation]], StaticEnvironment]:
    codes = {s: DEFAULT_CODES[s] for s in "GCE"}
    environment = StaticEnvironment(
        navigation=Ephemerides.from_navigation(read_navigation(str(DATA / "broadcast-nav.rnx")))
    )
    out = []
    for number, epoch in enumerate(read_epochs(str(DATA / "rover-0-5min.rnx"), codes)):
        if number >= epochs:
            break
        out.append(epoch_pseudoranges(epoch))
    return out, environment


def run(epochs, environment, options) -> list[float]:
    pipeline = GnssTightPipeline()
    state = pipeline.create(pipeline.resolve_options({"seed": 1, **options}), None)
    spent = []
    for epoch in epochs:
        start = time.perf_counter()
        _, state = pipeline.process(state, epoch, environment)
        spent.append(1000.0 * (time.perf_counter() - start))
    return spent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=200)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--filter", default="upf", choices=("upf", "pf", "ukf"))
    parser.add_argument("--particles", type=int, default=200)
    args = parser.parse_args()
    epochs, environment = load(args.epochs)
    common = {"filter": args.filter, "particles": args.particles}
    medians: dict[str, list[float]] = {name: [] for name in CONFIGS}
    every: dict[str, list[float]] = {name: [] for name in CONFIGS}
    for _ in range(args.reps):
        for name, options in CONFIGS.items():
            spent = run(epochs, environment, {**common, **options})
            medians[name].append(statistics.median(spent))
            every[name].extend(spent)
    for name in CONFIGS:
        per_rep = ", ".join(f"{m:.1f}" for m in medians[name])
        print(
            f"{name:9s} median ms/epoch per repetition: {per_rep}; all: {statistics.median(every[name]):.1f}"
        )


if __name__ == "__main__":
    main()
