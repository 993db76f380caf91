"""A neighbour broadcasting a wrong position, injected into cooperative runs (pure, deterministic).

In a faulty run one vehicle's published track is offset by ``offset_m`` in a drawn direction from a
uniformly drawn start for ``duration_s`` (a wrong map match, a receiver stuck on a reflection): its own
fixes are untouched, but every neighbour ranging to it reads a position ``offset_m`` off.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from edgepos.pipelines.base import NeighbourTrack
from edgepos.sim.faults import EARLIEST_START_S, FaultEvent, add_fault_flags


@dataclass(frozen=True)
class NeighbourFaults:
    """In a fraction ``run_fraction`` of runs, one vehicle broadcasts positions ``offset_m`` off for
    ``duration_s`` seconds."""

    run_fraction: float = 1.0
    offset_m: float = 20.0
    duration_s: float = 5.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.run_fraction <= 1.0:
            raise ValueError(f"--fault-runs must be in [0, 1], got {self.run_fraction}")
        if not (math.isfinite(self.offset_m) and 0.0 < self.offset_m <= 1e4):
            raise ValueError(f"--fault-offset must be in (0, 10000] m, got {self.offset_m}")
        if not 0.0 < self.duration_s <= 3600.0:
            raise ValueError(f"--fault-duration must be in (0, 3600] s, got {self.duration_s}")


@dataclass(frozen=True)
class NeighbourFault:
    """One run's fault: the event (``rsu_id`` holds the faulty vehicle's id, ``kind`` "position",
    ``size`` the offset in m) and the offset's direction (rad, site frame)."""

    event: FaultEvent
    direction: float

    def apply(self, track: NeighbourTrack) -> NeighbourTrack:
        """The track as broadcast: its points within the fault window moved by the offset."""
        dx = self.event.size * math.cos(self.direction)
        dy = self.event.size * math.sin(self.direction)
        points = tuple(
            dataclasses.replace(p, x=p.x + dx, y=p.y + dy) if self.event.active(p.t) else p
            for p in track.points
        )
        return NeighbourTrack(track.vehicle_id, points)


def draw(
    faults: NeighbourFaults, vehicle_ids: tuple[str, ...], first: float, last: float, rng: np.random.Generator
) -> NeighbourFault | None:
    """The run's fault (None in a fault-free run): vehicle, start in [first + 2 s, last - duration], direction."""
    if rng.random() >= faults.run_fraction:
        return None
    earliest = first + EARLIEST_START_S
    latest = max(earliest, last - faults.duration_s)
    start = float(rng.uniform(earliest, latest)) if latest > earliest else earliest
    vehicle = vehicle_ids[int(rng.integers(len(vehicle_ids)))]
    direction = float(rng.uniform(-math.pi, math.pi))
    event = FaultEvent(vehicle, "position", faults.offset_m, start, start + faults.duration_s)
    return NeighbourFault(event, direction)


def add_neighbour_fault_arguments(parser: argparse.ArgumentParser) -> None:
    """``--faults`` and the rate, size and duration of the injected neighbour faults."""
    defaults = NeighbourFaults()
    add_fault_flags(
        parser,
        "inject a neighbour broadcasting a wrong position and report the integrity figures against it",
        defaults.run_fraction,
        [
            (
                "--fault-offset",
                "M",
                defaults.offset_m,
                "how far off the faulty neighbour's broadcast position is (m, default {default})",
            )
        ],
        defaults.duration_s,
    )


def neighbour_faults_from(args: argparse.Namespace) -> NeighbourFaults | None:
    """The faults the command line asks for (None without --faults); ValueError naming a bad flag."""
    if not args.faults:
        return None
    return NeighbourFaults(args.fault_runs, args.fault_offset, args.fault_duration)
