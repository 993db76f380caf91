"""The integrity block of the GNSS evaluations (``edgepos eval gnss-rinex``): per epoch with a reference,
the fix's horizontal error against its protection level and state, counted as in eval/integrity.py
(misleading, hazardous, availability, detections, median protection level), plus the NEES of the fix's
covariance (raw and as the monitor inflates it), and a Stanford diagram on a GNSS scale."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgepos.core.integrity import OK
from edgepos.eval.integrity import stanford_figure
from edgepos.pipelines.integrity import EXCLUDED

STANFORD_MAX_M = 30.0
STANFORD_BINS = np.linspace(0.0, STANFORD_MAX_M, 151)  # 0.2 m


WINDOW_EPOCHS = 30
"""Epochs of the windows whose worst mean NEES is reported: multipath-correlated errors make the covariance
too small on stretches of tens of seconds, which a mean over minutes hides."""


def _worst_window(nees: np.ndarray, window: int) -> float | None:
    """The largest mean NEES over ``window`` consecutive scored epochs (of all of them when fewer)."""
    if nees.size == 0:
        return None
    if nees.size <= window:
        return float(nees.mean())
    sums = np.convolve(nees, np.ones(window), mode="valid")
    return float(sums.max() / window)


class GnssIntegrity:
    """Accumulates (error east-north, covariance, protection level, state, exclusions) per scored epoch."""

    def __init__(self) -> None:
        self.errors: list[np.ndarray] = []
        self.covariances: list[np.ndarray] = []
        self.levels: list[float | None] = []
        self.states: list[str] = []
        self.exclusions: list[int] = []

    def add(self, error_en: np.ndarray, fix: Any) -> None:
        self.errors.append(np.asarray(error_en, float))
        self.covariances.append(np.asarray(fix.position_cov, float))
        self.levels.append(fix.protection_level)
        self.states.append(fix.integrity)
        self.exclusions.append(
            sum(1 for use in fix.measurements if use.reason is not None and use.reason.startswith(EXCLUDED))
        )

    def subset(self, keep: slice) -> GnssIntegrity:
        out = GnssIntegrity()
        out.errors, out.covariances = self.errors[keep], self.covariances[keep]
        out.levels, out.states, out.exclusions = self.levels[keep], self.states[keep], self.exclusions[keep]
        return out

    def summary(self, alert_limit: float, inflation: float) -> dict[str, Any]:
        """The figures: counts as eval/integrity.py names them, and the mean NEES (2 dof) of the fixes'
        covariance, raw and times the monitor's inflation, with the fraction beyond the 99.9 % bound."""
        epochs = len(self.errors)
        errors = np.array([float(np.hypot(*e)) for e in self.errors])
        ok = np.array([s == OK for s in self.states], dtype=bool)
        level = np.array([np.nan if v is None else v for v in self.levels], dtype=float)
        nees = np.array([float(e @ np.linalg.solve(c, e)) for e, c in zip(self.errors, self.covariances)])
        with np.errstate(invalid="ignore"):
            misleading = ok & (errors > level)
        has_level = np.isfinite(level)
        bound = 13.8155  # chi-square 2 dof, 99.9 %
        return {
            "epochs": epochs,
            "alert_limit_m": alert_limit,
            "availability": float(ok.mean()) if epochs else None,
            "alarm_rate": float(np.mean([s == "alarm" for s in self.states])) if epochs else None,
            "unavailable_rate": float(np.mean([s == "unavailable" for s in self.states])) if epochs else None,
            "misleading": int(misleading.sum()),
            "misleading_rate": float(misleading.mean()) if epochs else None,
            "hazardous": int((ok & (errors > alert_limit)).sum()),
            "hazardous_rate": float((ok & (errors > alert_limit)).mean()) if epochs else None,
            "detections": int(sum(self.exclusions)),
            "median_protection_level_m": float(np.median(level[has_level])) if has_level.any() else None,
            "max_error_over_protection_level": float(np.nanmax(errors / level)) if has_level.any() else None,
            "mean_nees": float(nees.mean()) if epochs else None,
            "mean_nees_inflated": float(nees.mean() / inflation) if epochs else None,
            "worst_window_mean_nees": _worst_window(nees, WINDOW_EPOCHS),
            "beyond_999_fraction": float(np.mean(nees > bound)) if epochs else None,
            "beyond_999_fraction_inflated": float(np.mean(nees / inflation > bound)) if epochs else None,
        }

    def stanford_plot(self, alert_limit: float, title: str, path: Path) -> Path:
        """Error against protection level (epochs by colour, log scale), the diagonal and the alert limit."""
        errors = np.array([float(np.hypot(*e)) for e in self.errors])
        level = np.array([np.nan if v is None else v for v in self.levels], dtype=float)
        have = np.isfinite(level)
        top = STANFORD_MAX_M
        histogram, _, _ = np.histogram2d(
            np.minimum(errors[have], top - 1e-9), np.minimum(level[have], top - 1e-9), [STANFORD_BINS] * 2
        )
        s = self.summary(alert_limit, 1.0)
        caption = (
            f"misleading {s['misleading']}, hazardous {s['hazardous']} of {s['epochs']} epochs\n"
            f"availability {s['availability'] or 0.0:.3f}, unavailable {s['unavailable_rate'] or 0.0:.3f}"
        )
        return stanford_figure(histogram, STANFORD_BINS, alert_limit, caption, title, path)


def error_en(fix_ecef: np.ndarray, truth_ecef: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """East and north of the fix's error (m) at the reference position (``rotation`` ECEF to ENU there)."""
    enu = rotation @ (np.asarray(fix_ecef) - np.asarray(truth_ecef))
    return np.array(enu[:2])


def integrity_lines(summary: dict[str, Any]) -> Sequence[str]:
    """The block's lines for the terminal."""
    median = summary["median_protection_level_m"]
    return (
        (
            f"integrity (alert limit {summary['alert_limit_m']:g} m): availability {summary['availability']:.3f}, "
            f"alarm {summary['alarm_rate']:.3f}, unavailable {summary['unavailable_rate']:.3f}; misleading "
            f"{summary['misleading']}, hazardous {summary['hazardous']} of {summary['epochs']} epochs; detections "
            f"{summary['detections']}; median PL {'-' if median is None else f'{median:.2f}'} m"
        ),
        (
            f"NEES (2 dof): mean {summary['mean_nees']:.2f} ({summary['beyond_999_fraction']:.3f} beyond the 99.9 % "
            f"bound, worst {WINDOW_EPOCHS}-epoch mean {summary['worst_window_mean_nees']:.2f}); inflated: mean "
            f"{summary['mean_nees_inflated']:.2f} ({summary['beyond_999_fraction_inflated']:.3f})"
        ),
    )
