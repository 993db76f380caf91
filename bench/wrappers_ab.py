"""Same-process A/B of the wrappers around a pipeline (the lag window and the plausibility checks) of two
git revisions, around the same inner ``rsu_imu`` pipeline, interleaved.

``pipelines/lag.py``, ``lag_state.py`` and ``plausibility.py`` of each revision are written to a temporary
directory under their own module names (each importing the others by their new names) and wrapped, as the
registry does, around this tree's ``RsuImuPipeline``: both sides load the same way, and differ only in the
wrappers. Each side is warmed up by ten 20-epoch batches (its lag window as a stream leaves it), then
times the jittered 20-epoch batches ``bench/filter_step.py`` times (integrity monitor on, the defaults),
the rounds alternating which side goes first. Prints each side's minimum and 10th percentile of thread
CPU time per epoch, and whether the two sides gave the same fixes and states (pickled) for every batch.

    python bench/wrappers_ab.py [--a main] [--b HEAD] [--rounds 15]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from edgepos.core.compiled import warm_up
from edgepos.pipelines.base import InitialState
from edgepos.pipelines.rsu_imu import RsuImuPipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs

sys.path.insert(0, str(Path(__file__).resolve().parent))
from revision_modules import load_revision_modules

FILES = ("lag", "lag_state", "plausibility")
BATCH = 20


def load_revision(revision: str, tag: str, directory: Path) -> dict[str, ModuleType]:
    """The revision's wrapper modules as ``<name>_<tag>``."""
    return load_revision_modules(revision, "edgepos.pipelines", FILES, tag, directory)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", default="main", help="git revision of side A")
    parser.add_argument("--b", default="HEAD", help="git revision of side B")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--batches", type=int, default=40, help="batches per side and round")
    args = parser.parse_args()
    warm_up()
    scenario = rsu_imu_paper_scenario()
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(7))
    env = environment(scenario)
    x0 = scenario.initial_state
    initial = InitialState(x0[0], x0[3], x0[1], x0[4])
    rng = np.random.default_rng(11)
    later = epochs[200 : 200 + BATCH]
    batches = []
    for _ in range(args.batches):
        shifts = rng.uniform(-0.002, 0.002, BATCH).tolist()
        batches.append([dataclasses.replace(o, t=o.t + s) for s, epoch in zip(shifts, later) for o in epoch])
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as directory:
        sys.path.insert(0, directory)
        sides: dict[str, Any] = {}
        states: dict[str, bytes] = {}
        answers: dict[str, list[bytes]] = {}
        for side, revision in (("A", args.a), ("B", args.b)):
            modules = load_revision(revision, side.lower(), Path(directory))
            pipeline = modules["lag"].LagWindow(modules["plausibility"].Plausible(RsuImuPipeline()))
            state = pipeline.create(pipeline.resolve_options({}), initial)
            for first in range(0, 200, BATCH):
                _, state = pipeline.process(state, [o for e in epochs[first : first + BATCH] for o in e], env)
            sides[side], states[side] = pipeline, state
            answers[side] = [pickle.dumps(pipeline.process(state, batch, env)) for batch in batches]
        same = answers["A"] == answers["B"] and states["A"] == states["B"]
        cpu: dict[str, list[float]] = {side: [] for side in sides}
        for round_ in range(args.rounds):
            for side in sides if round_ % 2 == 0 else reversed(list(sides)):
                pipeline, state = sides[side], states[side]
                for batch in batches:
                    started = time.thread_time_ns()
                    pipeline.process(state, batch, env)
                    cpu[side].append((time.thread_time_ns() - started) / 1e3 / BATCH)
    print(
        f"A = {args.a}, B = {args.b}: {'the same fixes and states' if same else 'DIFFERENT fixes or states'}; "
        f"load average {load_before:.2f} before, {os.getloadavg()[0]:.2f} after"
    )
    for side, values in cpu.items():
        print(
            f"{side}  us per epoch of a {BATCH}-epoch jittered batch, thread CPU: min {min(values):7.2f}  "
            f"p10 {np.percentile(values, 10):7.2f}  median {np.median(values):7.2f}"
        )
    print(
        f"B - A at the 10th percentile: {np.percentile(cpu['B'], 10) - np.percentile(cpu['A'], 10):+.2f} us per epoch"
    )
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
