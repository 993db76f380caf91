"""Benchmark: the v2v_coop pipeline's cost per epoch by method and number of neighbours ranged.

One epoch is what a vehicle of the V2V paper's scenario sends every 0.2 s: a GNSS fix, a gyro yaw
rate, an odometer distance and a time of arrival from each of N neighbours, whose positions come
from published tracks (as the service reads them from the neighbours' sessions). For each method
and N = 1, 3, 8 and 16 it times the pipeline per epoch inside 20-epoch batches (state decoding and
encoding included), interleaved with the ``gps_dr`` epoch of the same data as the baseline, and
prints the median, the 90th percentile and the ratio to the baseline.

    python bench/cooperative.py [--batches N]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time

import numpy as np
from edgepos.core.observations import (
    SPEED_OF_LIGHT,
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    V2vRangeObservation,
)
from edgepos.pipelines.base import NeighbourTrack, StaticEnvironment, TrackPoint
from edgepos.pipelines.registry import get_pipeline

STEP = 0.2
SPEED = 15.0
BATCH = 20
NEIGHBOUR_COUNTS = (1, 3, 8, 16)
METHODS = ("gps", "ukf", "aug_ukf")


def scenario(
    count: int, epochs: int, rng: np.random.Generator
) -> tuple[list[list[Observation]], StaticEnvironment]:
    """A vehicle driving east among ``count`` neighbours 20-60 m away, and their tracks."""
    offsets = [
        (20.0 * math.cos(2 * math.pi * k / count) * (1 + k % 3), 20.0 * math.sin(2 * math.pi * k / count))
        for k in range(count)
    ]
    cov = tuple(tuple(float(i == j) * (1.0 if i < 2 else 0.25) for j in range(4)) for i in range(4))
    tracks = {
        f"peer-{k}": NeighbourTrack(
            f"peer-{k}",
            tuple(TrackPoint(n * STEP, SPEED * n * STEP + dx, dy, SPEED, 0.0, cov) for n in range(epochs)),
        )
        for k, (dx, dy) in enumerate(offsets)
    }
    observations = []
    for n in range(epochs):
        t, x = n * STEP, SPEED * n * STEP
        epoch: list[Observation] = [
            GnssFixObservation(t, x + rng.normal(0, 3.5), rng.normal(0, 3.5)),
            GyroObservation(t, rng.normal(0, 0.005)),
            OdometerObservation(t, distance=SPEED * STEP + rng.normal(0, 0.1)),
        ]
        epoch += [
            V2vRangeObservation(
                t, f"peer-{k}", toa=(math.hypot(dx, dy) + rng.normal(0, 2.0)) / SPEED_OF_LIGHT
            )
            for k, (dx, dy) in enumerate(offsets)
        ]
        observations.append(epoch)
    return observations, StaticEnvironment(tracks=tracks, vehicle_id="target")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--batches", type=int, default=40, help="timed 20-epoch batches per case (default 40)"
    )
    args = parser.parse_args()
    pipeline = get_pipeline("v2v_coop")
    epochs = BATCH * (args.batches + 2)
    print(
        f"v2v_coop per epoch (20-epoch batches, {args.batches} batches per case), {os.cpu_count()} cores, "
        f"{platform.python_implementation()} {platform.python_version()}, load average {os.getloadavg()[0]:.2f}"
    )
    print(
        f"{'method':>8}  {'neighbours':>10}  {'median us':>10}  {'p90 us':>8}  {'gps_dr us':>9}  {'ratio':>6}"
    )
    for count in NEIGHBOUR_COUNTS:
        observations, environment = scenario(count, epochs, np.random.default_rng(count))
        baseline_state = pipeline.create(pipeline.resolve_options({"method": "gps_dr"}), None)
        warm = [o for e in observations[:BATCH] for o in e]
        _, baseline_state = pipeline.process(baseline_state, warm, environment)
        states = {}
        for method in METHODS:
            states[method] = pipeline.create(pipeline.resolve_options({"method": method}), None)
            _, states[method] = pipeline.process(states[method], warm, environment)
        times: dict[str, list[float]] = {m: [] for m in (*METHODS, "gps_dr")}
        for b in range(1, args.batches + 1):
            batch = [o for e in observations[b * BATCH : (b + 1) * BATCH] for o in e]
            for method in (*METHODS, "gps_dr"):
                state = baseline_state if method == "gps_dr" else states[method]
                started = time.perf_counter()
                _, state = pipeline.process(state, batch, environment)
                times[method].append((time.perf_counter() - started) * 1e6 / BATCH)
                if method == "gps_dr":
                    baseline_state = state
                else:
                    states[method] = state
        baseline = statistics.median(times["gps_dr"])
        for method in METHODS:
            median = statistics.median(times[method])
            print(
                f"{method:>8}  {count:>10}  {median:>10.1f}  {np.percentile(times[method], 90):>8.1f}  "
                f"{baseline:>9.1f}  {median / baseline:>6.2f}"
            )
    print(f"load average {os.getloadavg()[0]:.2f} after")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
