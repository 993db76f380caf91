"""Benchmark: the v2x_federated pipeline's cost per epoch against the number of neighbours ranged.

One epoch is what a vehicle of the paper's scenario sends every 0.2 s: a GNSS fix, a gyro yaw rate,
an odometer distance and a V2V range to each of N neighbours, whose positions come from published
tracks (as the service reads them from the neighbours' sessions). For N = 0, 1, 2, 4, 8 and 16 it
times the pipeline per epoch inside 20-epoch batches (state decoding and encoding included), with
the GPS-only epoch (gnss_fix alone) timed interleaved in the same run as the baseline, and prints
the median, the 90th percentile and the ratio to the baseline.

    python bench/federated.py [--batches N]
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
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    V2vRangeObservation,
)
from edgepos.pipelines.base import NeighbourTrack, StaticEnvironment, TrackPoint
from edgepos.pipelines.registry import get_pipeline

STEP = 0.2
SPEED = 10.0
BATCH = 20
NEIGHBOUR_COUNTS = (0, 1, 2, 4, 8, 16)


def neighbour_offsets(count: int) -> list[tuple[float, float]]:
    """Neighbours 30 m apart along the road, alternating lanes 3.5 m either side of the target."""
    return [
        (30.0 * (k // 2 + 1) * (1 if k % 2 == 0 else -1), 3.5 * (1 if k % 4 < 2 else -1))
        for k in range(count)
    ]


def scenario(
    count: int, epochs: int, rng: np.random.Generator
) -> tuple[list[list[Observation]], StaticEnvironment]:
    """Observations per epoch of a target driving east at SPEED, and the neighbours' tracks."""
    offsets = neighbour_offsets(count)
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
            GnssFixObservation(t, x + rng.normal(0, 3.9), rng.normal(0, 3.9), None),
            GyroObservation(t, rng.normal(0, 0.005)),
            OdometerObservation(t, distance=SPEED * STEP + rng.normal(0, 0.1)),
        ]
        epoch += [
            V2vRangeObservation(t, f"peer-{k}", range=math.hypot(dx, dy) + rng.normal(0, 3.0))
            for k, (dx, dy) in enumerate(offsets)
        ]
        observations.append(epoch)
    return observations, StaticEnvironment(tracks=tracks, vehicle_id="target")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--batches", type=int, default=60, help="timed 20-epoch batches per case (default 60)"
    )
    args = parser.parse_args()
    pipeline = get_pipeline("v2x_federated")
    options = pipeline.resolve_options({})
    epochs = BATCH * (args.batches + 2)
    print(
        f"v2x_federated per epoch (20-epoch batches, {args.batches} batches per case), "
        f"{os.cpu_count()} cores, {platform.python_implementation()} {platform.python_version()}, "
        f"load average {os.getloadavg()[0]:.2f}"
    )
    print(f"{'neighbours':>10}  {'median us':>10}  {'p90 us':>8}  {'GPS-only us':>11}  {'ratio':>6}")
    for count in NEIGHBOUR_COUNTS:
        observations, environment = scenario(count, epochs, np.random.default_rng(count))
        gps_only = [[obs for obs in epoch if isinstance(obs, GnssFixObservation)] for epoch in observations]
        full_state = pipeline.create(options, None)
        gps_state = pipeline.create(options, None)
        # The first batch initialises and warms up both sessions; it is not timed.
        _, full_state = pipeline.process(
            full_state, [o for e in observations[:BATCH] for o in e], environment
        )
        _, gps_state = pipeline.process(gps_state, [o for e in gps_only[:BATCH] for o in e], environment)
        full_us: list[float] = []
        gps_us: list[float] = []
        for b in range(1, args.batches + 1):
            window = slice(b * BATCH, (b + 1) * BATCH)
            batch = [o for e in observations[window] for o in e]
            started = time.perf_counter()
            _, full_state = pipeline.process(full_state, batch, environment)
            full_us.append((time.perf_counter() - started) * 1e6 / BATCH)
            batch = [o for e in gps_only[window] for o in e]
            started = time.perf_counter()
            _, gps_state = pipeline.process(gps_state, batch, environment)
            gps_us.append((time.perf_counter() - started) * 1e6 / BATCH)
        median, baseline = statistics.median(full_us), statistics.median(gps_us)
        print(
            f"{count:>10}  {median:>10.1f}  {np.percentile(full_us, 90):>8.1f}  {baseline:>11.1f}  "
            f"{median / baseline:>6.2f}"
        )
    print(f"load average {os.getloadavg()[0]:.2f} after")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
