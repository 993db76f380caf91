"""Digest of the rsu_imu pipeline's answers over many cases: every fix and every returned state, hashed.

Run on two trees (PYTHONPATH pointing at each) to show that a change to the compiled path or the
Python around it leaves every answer bit-identical: option sets (filters, joint and averaged RSU
handling, gate off, 1-model and IMM banks, monitor on and off) x faults (one RSU's range biased,
which the monitor excludes) x jittered timestamps x a gap of 6.5 s that re-initialises, in 20-epoch batches
through the registry's pipeline (lag window and plausibility checks included).

    python bench/rsu_imu_digest.py [--epochs N]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import itertools
import pickle

import numpy as np
from edgepos.pipelines.base import InitialState
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs

OPTION_SETS = (
    {},
    {"integrity": False},
    {"filter": "ukf"},
    {"filter": "ekf", "integrity": False},
    {"rsu_handling": "average"},
    {"rsu_handling": "average", "filter": "ekf"},
    {"gate_probability": 0.0},
    {"models": ["ca"], "priority": []},
    {"models": ["cv", "ct", "singer"], "priority": [], "integrity": False},
    {"fault_exclusion": False},
)


def epochs_of(seed: int, count: int, fault: bool, jitter: bool, gap: bool):
    scenario = rsu_imu_paper_scenario()
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(seed))[:count]
    rng = np.random.default_rng(seed + 1000)
    out = []
    for k, epoch in enumerate(epochs):
        if gap and count // 2 <= k < count // 2 + 10:  # half a second without data
            continue
        shift = float(rng.uniform(-0.002, 0.002)) if jitter else 0.0
        if gap and k >= count // 2:
            shift += 6.0  # then 6 s more, beyond the default max_gap: the filter starts again
        moved = []
        for observation in epoch:
            changes = {"t": observation.t + shift}
            if fault and observation.kind == "rsu" and k >= 40 and observation is epoch[0]:
                changes["range"] = observation.range + 8.0  # the nearest RSU biased by 8 m
            moved.append(dataclasses.replace(observation, **changes))
        out.append(moved)
    return scenario, out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=160)
    args = parser.parse_args()
    pipeline = get_pipeline("rsu_imu")
    total = hashlib.sha256()
    cases = 0
    for index, (options, fault, jitter, gap) in enumerate(
        itertools.product(OPTION_SETS, (False, True), (False, True), (False, True))
    ):
        scenario, epochs = epochs_of(index, args.epochs, fault, jitter, gap)
        env = environment(scenario)
        resolved = pipeline.resolve_options(options)
        x0 = scenario.initial_state
        initial = InitialState(x0[0], x0[3], x0[1], x0[4]) if index % 3 else None
        state = pipeline.create(resolved, initial)
        case = hashlib.sha256()
        for first in range(0, len(epochs), 20):
            batch = [o for epoch in epochs[first : first + 20] for o in epoch]
            fixes, state = pipeline.process(state, batch, env)
            case.update(pickle.dumps(fixes, protocol=5))
            case.update(state)
        total.update(case.digest())
        cases += 1
    print(f"{cases} cases, {args.epochs} epochs each: {total.hexdigest()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
