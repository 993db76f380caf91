"""Benchmark: what late measurements cost the rsu_imu pipeline with its lag window, against in order.

The RSU + IMU paper scenario (20 Hz, 4 RSUs + gyro per epoch) is fed to the registered ``rsu_imu``
pipeline (lag window at its defaults, ``max_delay_s`` 1 s) as a vehicle would send it, in batches of
B epochs (each sent when its last epoch has happened): once in order, once with 30 % of the RSU
measurements 0.05-0.5 s late (``sim.delivery``: a batch holds what arrived since the previous one, so
late measurements land in later batches and the window replays from a checkpoint). The two deliveries
are timed interleaved, round after round, so that load on the machine hits both alike; each figure is
the median over rounds of CPU time per epoch of the scenario. Also printed: the session state's size
(in order and late) and how many epochs each late batch filtered again, and a check that both runs end
in the same filter state (replay is exact).

Target (issue 15): the cost of an epoch with 30 % late at most 3 x an in-order epoch.

    python bench/late_measurements.py [--rounds N] [--epochs K] [--batch-epochs 1,5,20] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from edgepos.core.compiled import warm_up
from edgepos.eval.rsu_imu_montecarlo import initial_state
from edgepos.pipelines import lag
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.delivery import LateDelivery, arrival_batches, arrival_times, in_order_batches
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs

TARGET_RATIO = 3.0


def _run(pipeline, options, start, batches, env) -> tuple[float, bytes, list[int]]:
    """CPU seconds of sending ``batches`` in order through a new session, the final state, and the
    fixes per batch."""
    state = pipeline.create(options, start)
    sizes = []
    began = time.process_time()
    for batch in batches:
        fixes, state = pipeline.process(state, batch, env)
        sizes.append(len(fixes))
    return time.process_time() - began, state, sizes


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--epochs", type=int, default=400, help="epochs of the scenario per run (default 400)"
    )
    parser.add_argument("--batch-epochs", default="1,5,20", help="batch sizes to measure (default 1,5,20)")
    parser.add_argument("--fraction", type=float, default=0.3)
    parser.add_argument("--max-delay", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    warm_up()
    scenario = rsu_imu_paper_scenario()
    env = environment(scenario)
    pipeline = get_pipeline("rsu_imu")
    options = pipeline.resolve_options({})
    start = initial_state(scenario)
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(args.seed))[: args.epochs]
    observations = [o for epoch in epochs for o in epoch]
    delivery = LateDelivery(args.fraction, args.max_delay)
    arrivals = arrival_times(observations, delivery, np.random.default_rng([args.seed, 1]))
    late_count = int(np.sum(arrivals > np.array([o.t for o in observations])))

    print(
        f"rsu_imu, paper scenario, {len(epochs)} epochs, {late_count} of {len(observations)} measurements late "
        f"({delivery.fraction:.0%} of RSU measurements, {delivery.min_delay_s:g}-{delivery.max_delay_s:g} s); "
        f"lag window max_delay_s {options['max_delay_s']:g} s; {args.rounds} rounds, medians; "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}, {platform.python_version()}"
    )
    header = (
        f"{'batch':>6} {'in order us/epoch':>18} {'late us/epoch':>14} {'ratio':>6} {'target':>7} "
        f"{'state in order B':>17} {'state late B':>13} {'fixes/batch late':>17} {'same end state':>15}"
    )
    print(header)
    results = []
    for batch_epochs in [int(b) for b in args.batch_epochs.split(",")]:
        ordered = in_order_batches(observations, batch_epochs)
        late = arrival_batches(observations, arrivals, batch_epochs)
        in_order_s, late_s = [], []
        for _ in range(args.rounds):
            seconds, state_in_order, _ = _run(pipeline, options, start, ordered, env)
            in_order_s.append(seconds)
            seconds, state_late, sizes = _run(pipeline, options, start, late, env)
            late_s.append(seconds)
        per_in_order = statistics.median(in_order_s) / len(epochs) * 1e6
        per_late = statistics.median(late_s) / len(epochs) * 1e6
        ratio = per_late / per_in_order
        same = lag._unpack(state_in_order).current == lag._unpack(state_late).current
        row = {
            "batch_epochs": batch_epochs,
            "in_order_us_per_epoch": per_in_order,
            "late_us_per_epoch": per_late,
            "ratio": ratio,
            "state_bytes_in_order": len(state_in_order),
            "state_bytes_late": len(state_late),
            "fixes_per_late_batch": float(np.mean(sizes)),
            "same_end_state": same,
        }
        results.append(row)
        print(
            f"{batch_epochs:>6} {per_in_order:>18.1f} {per_late:>14.1f} {ratio:>6.2f} "
            f"{'ok' if ratio <= TARGET_RATIO else 'MISSED':>7} {len(state_in_order):>17} {len(state_late):>13} "
            f"{np.mean(sizes):>17.2f} {same!s:>15}"
        )
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    if args.json is not None:
        args.json.write_text(
            json.dumps({"results": results, "load_average": os.getloadavg()[0]}, indent=2) + "\n"
        )
    return 0 if all(r["same_end_state"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
