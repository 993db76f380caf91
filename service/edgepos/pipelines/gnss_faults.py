"""Faults caught over time (issue 16, item 4): a persistence-aware innovation test for ``gnss_tight``.

A reflected (NLOS) or multipath signal in a street canyon stays biased for seconds, so one epoch's test is the
wrong unit: a satellite whose innovation (measured minus the filter's predicted range, or range rate) is
beyond the ``fault_probability`` chi-square(1) quantile is *suspect*; while suspect it is down-weighted (its
std raised so that its normalised innovation equals the threshold, a Huber-like weight); suspect for
``fault_persistence`` consecutive epochs, it is *excluded*, and stays excluded, its innovation still computed
every epoch against the prediction, until it has agreed for ``fault_recovery`` consecutive epochs. Range and
range rate are tracked separately (keys ``G05`` and ``G05/rate``). When more than half of an epoch's rows are
suspect the prediction, not the satellites, is in doubt: nothing is counted or changed that epoch (the
residual test's lost-track rule handles it).

The history is a plain dict, satellite key -> [suspect epochs in a row, agreeing epochs in a row, excluded 0/1,
time of the last update], kept in the session state and forgotten after ``_FORGET_S`` without the satellite.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from edgepos.core.measurements.gnss_kernel import range_rates_at
from edgepos.core.measurements.range_rate import RangeRateModel
from edgepos.core.motion import riss as layout
from edgepos.gnss.measurements import PseudorangeSet
from edgepos.pipelines.gnss_screening import (
    VELOCITY_BLOCK,
    chi2_threshold,
    group_rows,
    median,
    range_residuals,
)
from edgepos.pipelines.gnss_session import GnssSession

History = dict[str, list[float]]
_FORGET_S = 30.0
"""A satellite unseen this long starts again with a clean history (it has moved across the sky)."""

DEFAULT_FAULT_PROBABILITY = 0.99
DEFAULT_FAULT_PERSISTENCE = 3
DEFAULT_FAULT_RECOVERY = 3


@dataclass(frozen=True)
class FaultVerdict:
    """Per row of one epoch: excluded (bool), the std multiplier (>= 1) and the reason (None: clean)."""

    excluded: np.ndarray
    inflation: np.ndarray
    reasons: list[str | None]


def normalised_scores(residual: np.ndarray, variance: np.ndarray, groups: Sequence[str]) -> np.ndarray:
    """residual^2 / variance with each group's median removed when it has three or more rows (a receiver
    clock, or clock drift, moves a group alike)."""
    centred = np.array(residual, dtype=float)
    for members in group_rows(groups).values():
        if len(members) >= 3:
            centred[members] -= median(centred[members])
    scores: np.ndarray = centred**2 / variance
    return scores


def judge(
    history: History,
    keys: Sequence[str],
    scores: np.ndarray,
    t: float,
    probability: float,
    persistence: int,
    recovery: int,
    unit: str,
) -> FaultVerdict:
    """Update each key's history with this epoch's score and say which rows are excluded or down-weighted.
    ``unit`` names the quantity in the reasons ("range" or "range rate")."""
    n = len(keys)
    excluded = np.zeros(n, dtype=bool)
    inflation = np.ones(n)
    reasons: list[str | None] = [None] * n
    for key in [k for k, v in history.items() if t - v[3] > _FORGET_S]:
        del history[key]
    if n == 0 or probability <= 0.0:
        return FaultVerdict(excluded, inflation, reasons)
    threshold = chi2_threshold(probability)
    suspect = scores > threshold
    if suspect.sum() * 2 > n:
        for row, key in enumerate(keys):
            state = history.get(key)
            if state is not None and state[2]:
                excluded[row] = True
                reasons[row] = (
                    f"excluded over time: its {unit} innovation was beyond the {probability:g} gate for "
                    f"{persistence} epochs; held out (most of this epoch's innovations are large)"
                )
                state[3] = t
        return FaultVerdict(excluded, inflation, reasons)
    flagged: list[bool] = suspect.tolist()  # Python values: indexing numpy per row costs more than the row
    values: list[float] = scores.tolist()
    for row, key in enumerate(keys):
        state = history.setdefault(key, [0.0, 0.0, 0.0, t])
        if flagged[row]:
            state[0] += 1.0
            state[1] = 0.0
        else:
            state[1] += 1.0
            state[0] = 0.0
        state[3] = t
        if not state[2] and state[0] >= persistence:
            state[2] = 1.0
        elif state[2] and state[1] >= recovery:
            state[2] = 0.0
        score = values[row]
        if state[2]:
            excluded[row] = True
            if flagged[row]:
                reasons[row] = (
                    f"excluded over time: its {unit} innovation has been beyond the {probability:g} gate "
                    f"({score:.1f} > {threshold:.1f}) for {int(state[0])} epochs in a row; it returns after "
                    f"{recovery} agreeing epochs"
                )
            else:
                reasons[row] = (
                    f"excluded over time: its {unit} innovation agrees again ({score:.1f} <= "
                    f"{threshold:.1f}) for {int(state[1])} of the {recovery} epochs it must before it returns"
                )
        elif flagged[row]:
            inflation[row] = float(np.sqrt(score / threshold))
            reasons[row] = (
                f"{unit} innovation beyond the {probability:g} gate ({score:.1f} > {threshold:.1f}) for "
                f"{int(state[0])} epoch(s): std x {inflation[row]:.2f}; excluded if it persists "
                f"{persistence} epochs"
            )
    return FaultVerdict(excluded, inflation, reasons)


def fault_settings(options: Mapping[str, Any]) -> tuple[float, int, int]:
    """(probability, persistence, recovery) of a session; sessions stored before the options existed had
    no such test (probability 0)."""
    return (
        float(options.get("fault_probability", 0.0)),
        int(options.get("fault_persistence", DEFAULT_FAULT_PERSISTENCE)),
        int(options.get("fault_recovery", DEFAULT_FAULT_RECOVERY)),
    )


def range_innovations(
    session: GnssSession,
    centre: np.ndarray,
    prs: PseudorangeSet,
    known: np.ndarray,
    std: np.ndarray,
    rows: np.ndarray,
    predicted_cov: np.ndarray,
    predicted: np.ndarray | None = None,
) -> np.ndarray:
    """Normalised squared innovations of the pseudoranges in ``rows`` against the predicted state: per
    constellation the median removed (three or more) or the clock's predicted variance added; variance
    std^2 + the predicted position variance (trace), as the residual test's. ``predicted``: every row's
    pseudorange predicted at ``centre`` when the caller has it (one prediction serves the epoch's tests)."""
    residual, systems = range_residuals(session, centre, prs, known, std, rows, predicted)
    variance = std[rows] ** 2 + float(np.trace(predicted_cov[:3, :3]))
    for system, members in group_rows(systems).items():
        if len(members) < 3:
            clock = layout.CLOCK[system]
            variance[members] += predicted_cov[clock, clock] if system in session.clock_seen else 1e12
    return normalised_scores(residual, variance, systems)


def rate_innovations(
    session: GnssSession,
    centre: np.ndarray,
    prs: PseudorangeSet,
    std: np.ndarray,
    rows: np.ndarray,
    predicted_cov: np.ndarray,
    predicted: np.ndarray | None = None,
) -> np.ndarray:
    """The same for range rates: one clock drift for all (median removed), variance std^2 + the predicted
    velocity variance (trace); ``predicted`` every row's range rate at ``centre`` when the caller has it."""
    assert session.anchor is not None and prs.range_rate_mps is not None
    assert prs.sat_velocity is not None and prs.sat_clock_drift is not None
    if predicted is None:
        predicted = centre_rates(session.anchor, centre, prs, rows)
    residual = prs.range_rate_mps[rows] - predicted[rows]
    variance = std[rows] ** 2 + float(np.trace(predicted_cov[VELOCITY_BLOCK]))
    if rows.size < 3:
        variance = variance + predicted_cov[layout.DRIFT, layout.DRIFT]
    return normalised_scores(residual, variance, ["drift"] * rows.size)


def screen(
    session: GnssSession,
    t: float,
    keys: Sequence[str],
    scores: np.ndarray,
    rows: np.ndarray,
    unit: str,
) -> tuple[np.ndarray, np.ndarray, dict[int, str]]:
    """Apply the session's fault settings to ``rows`` with their scores: the rows kept, each kept row's std
    multiplier (aligned with the kept rows), and per row (excluded or down-weighted) the reason."""
    probability, persistence, recovery = fault_settings(session.options)
    verdict = judge(session.faults, keys, scores, t, probability, persistence, recovery, unit)
    reasons = {r: why for r, why in zip(rows.tolist(), verdict.reasons) if why is not None}
    keep = ~verdict.excluded
    return rows[keep], verdict.inflation[keep], reasons


def centre_rates(anchor: Any, centre: np.ndarray, prs: PseudorangeSet, rows: np.ndarray) -> np.ndarray:
    """Range rates predicted at ``centre`` for the rows ``rows`` of ``prs`` (others NaN), indexed by row: the
    range-rate tests of an epoch share one prediction."""
    assert prs.sat_velocity is not None and prs.sat_clock_drift is not None
    predicted = np.full(len(prs), np.nan)
    compiled = range_rates_at(
        anchor, centre[None, :], prs.sat_position[rows], prs.sat_velocity[rows], prs.sat_clock_drift[rows]
    )
    if compiled is not None:  # the kernel; each row's rate alone, as range_rate_test's own prediction
        predicted[rows] = compiled[0]
        return predicted
    rate_model = RangeRateModel.build(
        anchor, prs.sat_position[rows], prs.sat_velocity[rows], prs.sat_clock_drift[rows], np.ones(rows.size)
    )
    predicted[rows] = rate_model.predict(centre)
    return predicted
