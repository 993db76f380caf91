"""``edgepos eval gnss --faults``: a satellite ramp injected into the simulated drive, and the integrity
counts of each filter's fixes (as eval/integrity.py defines them: misleading, hazardous, availability,
detections, median protection level).

The ramp: one GPS satellite per run (the one with the most pseudoranges in it, so it is in view for the
ramp) gets a bias growing at ``rate`` m/s from ``START_FRACTION`` of the run, held at ``size`` m once
reached, to the end; a slowly growing reflection or a satellite clock running off."""

from __future__ import annotations

import argparse
import dataclasses
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from edgepos.core.integrity import ALARM, OK
from edgepos.core.observations import Observation, PseudorangeObservation
from edgepos.eval.integrity import COUNTERS
from edgepos.pipelines.base import Fix
from edgepos.pipelines.integrity import EXCLUDED

START_FRACTION = 0.3
RATE_BOUNDS = (0.01, 100.0)
SIZE_BOUNDS = (0.1, 10000.0)
PL_BINS = np.linspace(0.0, 100.0, 401)  # 0.25 m; the median protection level is read from it


@dataclass(frozen=True)
class Ramp:
    rate_mps: float
    size_m: float


def bounded(name: str, low: float, high: float) -> Any:
    """An argparse type: a float in [low, high] (argparse names the flag and exits 2 otherwise)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{name} must be in [{low:g}, {high:g}], got {text}")
        return value

    return parse


def inject(batches: list[list[Observation]], ramp: Ramp) -> tuple[list[list[Observation]], str, float]:
    """The batches with the ramp on one GPS satellite; its name (e.g. G05) and the ramp's start (s)."""
    counts = Counter(
        (o.system, o.prn) for batch in batches for o in batch if isinstance(o, PseudorangeObservation)
    )
    gps = [key for key, _ in counts.most_common() if key[0] == "G"] or [
        key for key, _ in counts.most_common()
    ]
    victim = gps[0]
    times = [o.t for batch in batches for o in batch]
    start = min(times) + START_FRACTION * (max(times) - min(times))
    out = []
    for batch in batches:
        changed: list[Observation] = []
        for o in batch:
            if isinstance(o, PseudorangeObservation) and (o.system, o.prn) == victim and o.t > start:
                bias = min(ramp.rate_mps * (o.t - start), ramp.size_m)
                o = dataclasses.replace(o, pseudorange=o.pseudorange + bias)
            changed.append(o)
        out.append(changed)
    return out, f"{victim[0]}{victim[1]:02d}", start


def empty() -> np.ndarray:
    """Counters then the protection levels' histogram, one array so that runs add up."""
    return np.zeros(len(COUNTERS) + PL_BINS.size - 1)


def tally(
    fixes: Sequence[tuple[Fix, frozenset[str]]],
    errors: Sequence[float],
    alert_limit: float,
    victim: str | None,
    start: float | None,
) -> np.ndarray:
    """One run's counts: ``fixes`` (each with the satellites a fault screen or the monitor left out) with
    their horizontal ``errors`` (m); ``victim`` the ramped satellite and ``start`` the ramp's start (None
    without a fault). ``exclusions`` counts the monitor's; a faulty run is detected at the first epoch after
    the start that leaves the victim out (any screen) or fails a test (alarm with the protection level
    within the alert limit: an alarm for a level above it says nothing about the fault)."""
    counts = dict.fromkeys(COUNTERS, 0.0)
    histogram = np.zeros(PL_BINS.size - 1)
    detected: float | None = None
    faulty = victim is not None and start is not None
    for (fix, left_out), error in zip(fixes, errors, strict=True):
        counts["epochs"] += 1
        counts[fix.integrity] += 1
        active = faulty and start is not None and fix.t > start
        for use in fix.measurements:
            if use.reason is not None and use.reason.startswith(EXCLUDED):
                counts["exclusions"] += 1
                if not (active and victim is not None and victim in use.reason):
                    counts["false_exclusions"] += 1
        failed_test = (
            fix.integrity == ALARM
            and fix.protection_level is not None
            and fix.protection_level <= alert_limit
        )
        if active and detected is None and (victim in left_out or failed_test):
            detected = fix.t
        if fix.protection_level is None:
            continue
        if fix.integrity == OK:
            counts["misleading"] += error > fix.protection_level
            counts["hazardous"] += error > alert_limit
        index = int(np.searchsorted(PL_BINS, fix.protection_level, side="right")) - 1
        histogram[min(index, histogram.size - 1)] += 1
    if faulty and start is not None:
        counts["faulty_runs"] = 1
        if detected is not None:
            counts["detected_runs"] = 1
            counts["detection_delay_s"] = detected - start
    return np.concatenate([[counts[name] for name in COUNTERS], histogram])


def summary(total: np.ndarray, alert_limit: float) -> dict[str, Any]:
    """The integrity block of an algorithm's summed counts."""
    value = dict(zip(COUNTERS, total[: len(COUNTERS)], strict=True))
    histogram = total[len(COUNTERS) :]
    epochs = max(value["epochs"], 1.0)
    median = None
    if histogram.sum():
        cumulative = np.cumsum(histogram)
        index = int(np.searchsorted(cumulative, cumulative[-1] / 2.0))
        median = float(0.5 * (PL_BINS[index] + PL_BINS[index + 1]))
    detected = value["detected_runs"]
    return {
        "epochs": int(value["epochs"]),
        "alert_limit_m": alert_limit,
        "availability": value["ok"] / epochs,
        "alarm_rate": value["alarm"] / epochs,
        "unavailable_rate": value["unavailable"] / epochs,
        "misleading": int(value["misleading"]),
        "misleading_rate": value["misleading"] / epochs,
        "hazardous": int(value["hazardous"]),
        "hazardous_rate": value["hazardous"] / epochs,
        "detections": int(value["exclusions"]),
        "false_exclusions": int(value["false_exclusions"]),
        "faulty_runs": int(value["faulty_runs"]),
        "detected_runs": int(detected),
        "mean_detection_delay_s": value["detection_delay_s"] / detected if detected else None,
        "median_protection_level_m": median,
    }
