"""Faults injected into simulated RSU measurements, to test integrity monitoring (pure, deterministic).

A faulty run has one RSU whose measurements go wrong for a while: a step in its range (a wrong
surveyed position along the line of sight, a reflection, a biased clock) or an offset in its
bearing (a rotated antenna array). The fault starts at a uniformly drawn time and lasts
``duration_s``; everything else is as simulated.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.core.observations import Observation, RsuObservation

#: The fault starts no earlier than this (s): the filter has settled and no fault hides in its start.
EARLIEST_START_S = 2.0


@dataclass(frozen=True)
class RsuFaults:
    """In a fraction ``run_fraction`` of runs, one RSU's range gets ``range_bias_m`` or its bearing
    ``bearing_offset_rad`` (one of the two, each equally likely when both are non-zero) for
    ``duration_s`` seconds."""

    run_fraction: float = 0.1
    range_bias_m: float = 5.0
    bearing_offset_rad: float = 0.05
    duration_s: float = 10.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.run_fraction <= 1.0:
            raise ValueError(f"--fault-runs must be in [0, 1], got {self.run_fraction}")
        if not (math.isfinite(self.range_bias_m) and math.isfinite(self.bearing_offset_rad)):
            raise ValueError("fault sizes must be finite")
        if abs(self.bearing_offset_rad) > math.pi:
            raise ValueError(
                f"--fault-bearing-offset must be within [-pi, pi], got {self.bearing_offset_rad}"
            )
        if self.range_bias_m == 0.0 and self.bearing_offset_rad == 0.0:
            raise ValueError("a fault needs a non-zero --fault-range-bias or --fault-bearing-offset")
        if not 0.0 < self.duration_s <= 3600.0:
            raise ValueError(f"--fault-duration must be in (0, 3600] s, got {self.duration_s}")


@dataclass(frozen=True)
class FaultEvent:
    """The fault of one run: which RSU, what, and when (``start`` <= t < ``end``)."""

    rsu_id: str
    kind: str  # "range" or "bearing"
    size: float  # m or rad
    start: float
    end: float

    def active(self, t: float) -> bool:
        return self.start <= t < self.end


def inject(
    observations: Sequence[Observation], faults: RsuFaults, rng: np.random.Generator
) -> tuple[list[Observation], FaultEvent | None]:
    """The run's observations with its fault applied (or unchanged, with None, in a fault-free run).

    The faulty RSU is drawn among those heard during the fault window, so that the fault is seen."""
    observations = list(observations)
    times = [o.t for o in observations]
    if not times or rng.random() >= faults.run_fraction:
        return observations, None
    first, last = min(times), max(times)
    latest_start = max(first + EARLIEST_START_S, last - faults.duration_s)
    start = (
        float(rng.uniform(first + EARLIEST_START_S, latest_start))
        if latest_start > first + EARLIEST_START_S
        else first
    )
    end = start + faults.duration_s
    heard = sorted({o.rsu_id for o in observations if isinstance(o, RsuObservation) and start <= o.t < end})
    if not heard:
        return observations, None
    rsu_id = heard[int(rng.integers(len(heard)))]
    kinds = [
        kind
        for kind, size in (("range", faults.range_bias_m), ("bearing", faults.bearing_offset_rad))
        if size
    ]
    kind = kinds[int(rng.integers(len(kinds)))]
    size = faults.range_bias_m if kind == "range" else faults.bearing_offset_rad
    event = FaultEvent(rsu_id, kind, size, start, end)
    faulted: list[Observation] = []
    for observation in observations:
        if (
            isinstance(observation, RsuObservation)
            and observation.rsu_id == rsu_id
            and event.active(observation.t)
        ):
            if kind == "range":
                observation = dataclasses.replace(observation, range=observation.range + size)
            else:
                bearing = math.remainder(observation.bearing + size, math.tau)
                observation = dataclasses.replace(observation, bearing=bearing)
        faulted.append(observation)
    return faulted, event


def add_fault_flags(
    parser: argparse.ArgumentParser,
    faults_help: str,
    run_fraction: float,
    sizes: Sequence[tuple[str, str, float, str]],
    duration_s: float,
) -> None:
    """The flags every ``edgepos eval ... --faults`` shares: ``--faults`` (``faults_help``), ``--fault-runs``,
    one flag per fault size (flag, metavar, default, what it sets, with ``{default}`` where its default goes)
    and ``--fault-duration``."""
    parser.add_argument("--faults", action="store_true", help=faults_help)
    flags = [
        ("--fault-runs", "F", run_fraction, "the fraction of runs with a fault (default {default})"),
        *sizes,
        ("--fault-duration", "S", duration_s, "how long a fault lasts (s, default {default})"),
    ]
    for flag, metavar, default, what in flags:
        parser.add_argument(
            flag,
            metavar=metavar,
            type=float,
            default=default,
            help="with --faults, " + what.format(default=f"{default:g}"),
        )


def add_fault_arguments(parser: argparse.ArgumentParser) -> None:
    """``--faults`` and the sizes and rates of the injected faults (see :func:`faults_from`)."""
    defaults = RsuFaults()
    add_fault_flags(
        parser,
        "inject RSU faults (range bias steps or bearing offsets) and report the integrity figures against them",
        defaults.run_fraction,
        [
            (
                "--fault-range-bias",
                "M",
                defaults.range_bias_m,
                "the range step of a faulty RSU (m, default {default}; 0: none)",
            ),
            (
                "--fault-bearing-offset",
                "RAD",
                defaults.bearing_offset_rad,
                "the bearing offset of a faulty RSU (rad, default {default}; 0: none)",
            ),
        ],
        defaults.duration_s,
    )


def faults_from(args: argparse.Namespace) -> RsuFaults | None:
    """The faults the command line asks for (None without --faults); ValueError naming a bad flag."""
    if not args.faults:
        return None
    return RsuFaults(args.fault_runs, args.fault_range_bias, args.fault_bearing_offset, args.fault_duration)
