"""Integrity figures of an evaluation: how often the protection level failed, and a Stanford diagram.

Per epoch with a fix, against the truth (horizontal error e, protection level PL, alert limit AL):

* ``misleading``: e > PL while the fix says ``ok`` (the integrity risk bounds its rate);
* ``hazardous``: e > AL while the fix says ``ok`` (the alert limit was trusted and broken);
* ``availability``: the fraction of epochs that say ``ok``;
* ``detections``: measurements excluded by fault detection (``false_exclusions`` those outside any
  injected fault), and of the runs with an injected fault, those in which the fault was detected
  (excluded or alarmed on while active) and how long after its start.

The Stanford diagram counts epochs by (error, protection level) in STANFORD_BINS (the last bin takes
everything beyond); the regions are e <= PL (nominal), PL < e <= AL (misleading) and e > AL
(hazardous when not in alarm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from edgepos.core.integrity import ALARM, OK
from edgepos.core.observations import Observation, RsuObservation, V2vRangeObservation
from edgepos.eval.plots import require_matplotlib
from edgepos.pipelines.base import Fix
from edgepos.sim.faults import FaultEvent

EXCLUDED = "excluded by fault detection"
COUNTERS = (
    "epochs",
    "ok",
    "alarm",
    "unavailable",
    "misleading",
    "hazardous",
    "exclusions",
    "false_exclusions",
    "faulty_runs",
    "detected_runs",
    "detection_delay_s",
)
STANFORD_MAX_M = 3.0
STANFORD_BINS = np.linspace(0.0, STANFORD_MAX_M, 151)  # 2 cm: the median protection level is read from it


def _empty_counts() -> np.ndarray:
    return np.zeros(len(COUNTERS))


def _empty_diagram() -> np.ndarray:
    return np.zeros((STANFORD_BINS.size - 1, STANFORD_BINS.size - 1))


@dataclass
class IntegrityTally:
    """Counters (``COUNTERS``) and the Stanford histogram (error bin x protection-level bin)."""

    counts: np.ndarray = field(default_factory=_empty_counts)
    diagram: np.ndarray = field(default_factory=_empty_diagram)
    scale: float = 1.0
    """The diagram's bins are STANFORD_BINS times this (m): 1 for rsu_imu, larger for metre-level fixes."""

    def __add__(self, other: IntegrityTally) -> IntegrityTally:
        return IntegrityTally(self.counts + other.counts, self.diagram + other.diagram, self.scale)

    def count(self, name: str) -> float:
        return float(self.counts[COUNTERS.index(name)])

    def median_protection_level(self) -> float | None:
        """The median protection level of the epochs that have one, interpolated within its 2 cm bin
        (the last bin holds everything beyond STANFORD_MAX_M)."""
        marginal = self.diagram.sum(axis=0)
        total = marginal.sum()
        if total == 0:
            return None
        cumulative = np.cumsum(marginal)
        index = int(np.searchsorted(cumulative, total / 2.0))
        below = cumulative[index - 1] if index else 0.0
        width = STANFORD_BINS[index + 1] - STANFORD_BINS[index]
        return self.scale * float(STANFORD_BINS[index] + width * (total / 2.0 - below) / marginal[index])

    def summary(self, alert_limit: float) -> dict[str, Any]:
        """The figures the evaluation's JSON carries."""
        epochs = max(self.count("epochs"), 1.0)
        faulty = self.count("faulty_runs")
        detected = self.count("detected_runs")
        return {
            "epochs": int(self.count("epochs")),
            "alert_limit_m": alert_limit,
            "availability": self.count("ok") / epochs,
            "alarm_rate": self.count("alarm") / epochs,
            "unavailable_rate": self.count("unavailable") / epochs,
            "misleading": int(self.count("misleading")),
            "misleading_rate": self.count("misleading") / epochs,
            "hazardous": int(self.count("hazardous")),
            "hazardous_rate": self.count("hazardous") / epochs,
            "detections": int(self.count("exclusions")),
            "false_exclusions": int(self.count("false_exclusions")),
            "faulty_runs": int(faulty),
            "detected_runs": int(detected),
            "mean_detection_delay_s": self.count("detection_delay_s") / detected if detected else None,
            "median_protection_level_m": self.median_protection_level(),
        }


def _bin(value: float) -> int:
    index = int(np.searchsorted(STANFORD_BINS, value, side="right")) - 1
    return min(index, STANFORD_BINS.size - 2)


def _source(observation: Observation) -> str | None:
    """The RSU or neighbour vehicle a measurement depends on (what a fault event names)."""
    if isinstance(observation, RsuObservation):
        return observation.rsu_id
    if isinstance(observation, V2vRangeObservation):
        return observation.peer_vehicle_id
    return None


def tally(
    fixes: Sequence[Fix],
    truth_xy: np.ndarray,
    times: np.ndarray,
    observations: Sequence[Observation],
    alert_limit: float,
    event: FaultEvent | None,
    scale: float = 1.0,
) -> IntegrityTally:
    """The integrity figures of one run: ``fixes`` against the truth ``truth_xy`` (K x 2) at ``times``
    (the fixes' epochs, in order), with the run's ``observations`` (one batch) and its fault ``event``."""
    result = IntegrityTally(scale=scale)
    counts = dict.fromkeys(COUNTERS, 0.0)
    detected_at: float | None = None
    for fix, (true_x, true_y), t in zip(fixes, truth_xy, times, strict=True):
        counts["epochs"] += 1
        counts[fix.integrity] += 1
        for use in fix.measurements:
            if use.reason is None or not use.reason.startswith(EXCLUDED):
                continue
            counts["exclusions"] += 1
            observation = observations[use.index]
            hit = event is not None and _source(observation) == event.rsu_id and event.active(observation.t)
            if not hit:
                counts["false_exclusions"] += 1
            elif detected_at is None:
                detected_at = float(t)
        if event is not None and detected_at is None and fix.integrity == ALARM and event.active(float(t)):
            detected_at = float(t)
        if fix.protection_level is None or fix.x is None or fix.y is None:
            continue
        error = float(np.hypot(fix.x - true_x, fix.y - true_y))
        if fix.integrity == OK:
            counts["misleading"] += error > fix.protection_level
            counts["hazardous"] += error > alert_limit
        result.diagram[_bin(error / scale), _bin(fix.protection_level / scale)] += 1
    if event is not None:
        counts["faulty_runs"] = 1
        if detected_at is not None:
            counts["detected_runs"] = 1
            counts["detection_delay_s"] = detected_at - event.start
    result.counts = np.array([counts[name] for name in COUNTERS])
    return result


def stanford_plot(tally_: IntegrityTally, alert_limit: float, title: str, path: Path) -> Path:
    """A Stanford diagram of ``tally_`` (error against protection level, epochs by colour on a log
    scale) with the diagonal, the alert limit and the counts of its regions."""
    summary = tally_.summary(alert_limit)
    caption = (
        f"misleading {summary['misleading']}, hazardous {summary['hazardous']} of {summary['epochs']} epochs\n"
        f"availability {summary['availability']:.4f}"
    )
    return stanford_figure(tally_.diagram, STANFORD_BINS * tally_.scale, alert_limit, caption, title, path)


def stanford_figure(
    histogram: np.ndarray, bins: np.ndarray, alert_limit: float, caption: str, title: str, path: Path
) -> Path:
    """Draw a Stanford diagram to ``path``: ``histogram`` counts epochs by error bin (rows) and
    protection-level bin (columns) over ``bins`` (m), shown on a log colour scale with the diagonal, the
    alert limit and ``caption`` (the regions' counts)."""
    from matplotlib.colors import LogNorm

    pyplot = require_matplotlib()
    top = float(bins[-1])
    figure, axes = pyplot.subplots(figsize=(6, 5), dpi=110)
    try:
        counts = np.ma.masked_equal(histogram.T, 0)  # rows: protection level, columns: error
        if counts.count():
            mesh = axes.pcolormesh(bins, bins, counts, norm=LogNorm(), cmap="viridis")
            figure.colorbar(mesh, ax=axes, label="epochs")
        axes.plot([0, top], [0, top], color="black", linewidth=1)
        axes.axvline(alert_limit, color="red", linewidth=1, linestyle="--")
        axes.axhline(alert_limit, color="red", linewidth=1, linestyle="--")
        axes.text(0.98 * top, 0.04 * top, caption, ha="right", fontsize=8)
        axes.set_xlim(0, top)
        axes.set_ylim(0, top)
        axes.set_xlabel("horizontal position error (m)")
        axes.set_ylabel("horizontal protection level (m)")
        axes.set_title(title)
        figure.tight_layout()
        path.parent.mkdir(parents=True, exist_ok=True)
        figure.savefig(path)
    finally:
        pyplot.close(figure)
    return path
