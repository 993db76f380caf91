"""What a ``gnss_tight`` epoch's measurements must pass before the filter update: a snapshot test on the
epoch's own least-squares residuals (as the baseline does), a residual test of each pseudorange against the
predicted state, and the same for range rates. Each exclusion is reported with its reason. Split from
``gnss_tight``."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.stats import chi2

from edgepos.core.compiled import compiled_enabled
from edgepos.core.measurements.gnss_kernel import pseudoranges_at, range_rates_at
from edgepos.core.measurements.gnss_raim_kernel import snapshot_round
from edgepos.core.measurements.pseudorange import PseudorangeModel
from edgepos.core.measurements.range_rate import RangeRateModel
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GnssOnlyModel, RissModel
from edgepos.core.numerics import FloatArray
from edgepos.gnss.measurements import PseudorangeSet
from edgepos.gnss.orbits import sagnac_range
from edgepos.gnss.spp import SppConfig
from edgepos.pipelines.base import (
    MeasurementUse,
)
from edgepos.pipelines.gnss_session import GnssSession, session_covariance

DopplerUses = dict[int, tuple[bool, str | None]]
"""Per observation index, whether its Doppler entered the update and, if not, why."""

VELOCITY_BLOCK = np.ix_([layout.VE, layout.VN, layout.VU], [layout.VE, layout.VN, layout.VU])
"""The velocity block's index arrays, built once (``np.ix_`` costs more than the indexing it serves)."""


def range_rate_test(
    session: GnssSession,
    centre: np.ndarray,
    prs: PseudorangeSet,
    std: np.ndarray,
    rows: np.ndarray,
    dt: float,
    model: RissModel | GnssOnlyModel,
    indices: list[int],
    doppler: DopplerUses,
    predicted_cov: np.ndarray | None = None,
    predicted: np.ndarray | None = None,
) -> np.ndarray:
    """The pseudorange residual test's counterpart for range rates: residual = measured - predicted, the
    median removed when three or more (one clock drift moves them all alike), else the drift's variance
    added; variance std^2 + the predicted velocity variance (trace; ``predicted_cov`` when the caller has
    it). ``predicted``: every row's range rate at ``centre`` (gnss_faults.centre_rates) when the caller has
    it. Returns the rows kept."""
    probability = session.options["gate_probability"]
    if probability <= 0.0 or rows.size == 0:
        return rows
    assert session.anchor is not None and prs.range_rate_mps is not None
    assert prs.sat_velocity is not None and prs.sat_clock_drift is not None
    if predicted is None:
        compiled = range_rates_at(
            session.anchor,
            centre[None, :],
            prs.sat_position[rows],
            prs.sat_velocity[rows],
            prs.sat_clock_drift[rows],
        )
        if compiled is not None:  # the kernel, as gnss_faults.centre_rates
            residual = prs.range_rate_mps[rows] - compiled[0]
        else:
            rate_model = RangeRateModel.build(
                session.anchor,
                prs.sat_position[rows],
                prs.sat_velocity[rows],
                prs.sat_clock_drift[rows],
                std[rows],
            )
            residual = prs.range_rate_mps[rows] - rate_model.predict(centre)
    else:
        residual = prs.range_rate_mps[rows] - predicted[rows]
    if predicted_cov is None:
        predicted_cov = session_covariance(session) + model.process_noise(dt)
    variance = std[rows] ** 2 + float(np.trace(predicted_cov[VELOCITY_BLOCK]))
    if rows.size >= 3:
        residual = residual - median(residual)
    else:
        variance = variance + predicted_cov[layout.DRIFT, layout.DRIFT]
    score = residual**2 / variance
    threshold = chi2_threshold(probability)
    failed = score > threshold
    for r, value in zip(rows[failed], score[failed]):
        doppler[indices[r]] = (
            False,
            f"failed the range-rate residual test: {value:.1f} > {threshold:.1f} (chi-square, 1 dof)",
        )
    kept: np.ndarray = rows[~failed]
    return kept


def snapshot_std(elevation: np.ndarray, corrected: np.ndarray | None = None) -> np.ndarray:
    """The least-squares baseline's pseudorange noise model (gnss/spp.py), sqrt(a^2 + b^2 / sin^2 el), with
    its own a, b for differentially corrected rows: the snapshot test judges residuals as the baseline
    does, whatever noise the filter assumes."""
    config = SppConfig()
    sin_el = np.maximum(np.sin(elevation), 0.05)
    std: FloatArray = np.sqrt(config.sigma_a_m**2 + (config.sigma_b_m / sin_el) ** 2)
    if corrected is None:
        return std
    chosen: FloatArray = np.where(
        corrected, np.sqrt(config.corrected_sigma_a_m**2 + (config.corrected_sigma_b_m / sin_el) ** 2), std
    )
    return chosen


def snapshot_test(
    session: GnssSession,
    receiver: np.ndarray,
    prs: PseudorangeSet,
    known: np.ndarray,
    std: np.ndarray,
    rows: np.ndarray,
    indices: list[int],
    uses: dict[int, MeasurementUse],
) -> np.ndarray:
    """Fault detection and exclusion on this epoch's pseudoranges alone, as the least-squares baseline does.

    Linearised at the predicted position: weighted least squares for a position correction and one clock
    per constellation; while the chi-square test of the weighted post-fit residuals fails, the pseudorange
    with the largest standardised residual (divided by sqrt(1 - leverage)) is excluded. Unlike a gate centred
    on the prediction it does not depend on the filter's history, so a persistent NLOS bias the filter has
    already followed is still found. ``receiver``: the predicted position (ECEF). Returns the rows kept."""
    options = session.options
    probability = options["fde_probability"]
    if probability <= 0.0 or options["max_exclusions"] <= 0 or rows.size == 0:
        return rows
    fit = _SnapshotFit(receiver, prs, known, std)
    keep = rows.copy()
    for _ in range(options["max_exclusions"]):
        result = fit.round(keep)
        if result is None:
            break  # too few rows, or a singular geometry: nothing to test against
        statistic, dof, worst, standardised = result
        if not math.isfinite(statistic) or statistic <= chi2_threshold(probability, dof):
            break
        i = indices[keep[worst]]
        uses[i] = MeasurementUse(
            i,
            "pseudorange",
            False,
            f"excluded by the snapshot test: {statistic:.1f} > {chi2_threshold(probability, dof):.1f} "
            f"(chi-square, {dof} dof), largest standardised residual {standardised:.1f}",
        )
        keep = np.delete(keep, worst)
    return keep


class _SnapshotFit:
    """The snapshot test's weighted least-squares rounds at one receiver position: by the compiled kernel
    (core/measurements/gnss_raim_kernel.py ``snapshot_kernel``) unless ``EDGEPOS_NUMBA=0`` or it declines a
    round, else by the numpy round here (its reference)."""

    def __init__(self, receiver: np.ndarray, prs: PseudorangeSet, known: np.ndarray, std: np.ndarray) -> None:
        self.receiver, self.prs, self.known, self.std = receiver, prs, known, std
        self.compiled = compiled_enabled()
        labels = sorted(set(prs.systems))
        self.group = np.array([labels.index(s) for s in prs.systems], dtype=np.int64)
        self._geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def round(self, keep: np.ndarray) -> tuple[float, int, int, float] | None:
        """(chi-square statistic of the weighted post-fit residuals, its degrees of freedom, the position in
        ``keep`` of the largest standardised residual (divided by sqrt(1 - leverage)), that residual); None
        when there are fewer than 2 degrees of freedom or the geometry is singular."""
        if self.compiled:
            prs = self.prs
            result = snapshot_round(
                self.receiver, prs.sat_position, prs.pseudorange_m, self.known, self.std, self.group, keep
            )
            if result is not None:
                return result
            if keep.size - 3 - len(set(self.group[keep].tolist())) < 2:
                return None
        return self._numpy_round(keep)

    def _numpy_round(self, keep: np.ndarray) -> tuple[float, int, int, float] | None:
        if self._geometry is None:
            geometric = sagnac_range(self.prs.sat_position, self.receiver)
            residual = self.prs.pseudorange_m - geometric - self.known
            line_of_sight = (self.receiver - self.prs.sat_position) / geometric[:, None]
            self._geometry = (np.array(self.prs.systems), residual, line_of_sight)
        systems, residual, line_of_sight = self._geometry
        present = sorted(set(systems[keep]))
        design = np.zeros((keep.size, 3 + len(present)))
        design[:, :3] = line_of_sight[keep]
        for column, system in enumerate(present):
            design[systems[keep] == system, 3 + column] = 1.0
        dof = keep.size - design.shape[1]
        if dof < 2:
            return None
        root = 1.0 / self.std[keep]
        weighted = design * root[:, None]
        normal = weighted.T @ weighted
        try:
            inverse = np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            return None
        normalised = (residual[keep] - design @ (inverse @ (weighted.T @ (residual[keep] * root)))) * root
        statistic = float(normalised @ normalised)
        leverage = np.einsum("ij,jk,ik->i", weighted, inverse, weighted)
        standardised = np.abs(normalised) / np.sqrt(np.maximum(1.0 - leverage, 1e-6))
        worst = int(np.argmax(standardised))
        return statistic, dof, worst, float(standardised[worst])


def range_residuals(
    session: GnssSession,
    centre: np.ndarray,
    prs: PseudorangeSet,
    known: np.ndarray,
    std: np.ndarray,
    rows: np.ndarray,
    predicted: np.ndarray | None = None,
) -> tuple[np.ndarray, list[str]]:
    """The pseudoranges in ``rows`` minus their prediction at ``centre``, and each row's constellation;
    ``predicted``: every row's pseudorange at ``centre`` when the caller has it (one prediction per epoch
    serves the residual test and the fault test over time), else predicted here."""
    assert session.anchor is not None
    systems = [prs.systems[r] for r in rows.tolist()]
    if predicted is None:
        compiled = pseudoranges_at(
            session.anchor, centre[None, :], prs.sat_position[rows], systems, known[rows]
        )
        if compiled is not None:  # the kernel, as gnss_integrity.linearisation_ranges
            return prs.pseudorange_m[rows] - compiled[0], systems
        model_pr = PseudorangeModel.build(
            session.anchor, prs.sat_position[rows], systems, known[rows], std[rows]
        )
        return prs.pseudorange_m[rows] - model_pr.predict(centre), systems
    return prs.pseudorange_m[rows] - predicted[rows], systems


def residual_test(
    session: GnssSession,
    centre: np.ndarray,
    prs: PseudorangeSet,
    known: np.ndarray,
    std: np.ndarray,
    rows: np.ndarray,
    dt: float,
    model: RissModel | GnssOnlyModel,
    indices: list[int],
    uses: dict[int, MeasurementUse],
    predicted_cov: np.ndarray | None = None,
    predicted: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """RAIM-like screening of each pseudorange against the predicted state.

    Residual = measured - predicted; per constellation with three or more satellites its median is
    removed (a clock error moves them all alike), otherwise the clock variance widens the test. The
    variance is std^2 plus the predicted position variance (trace). Returns the rows kept and whether the
    prediction is lost (more than half of at least four pseudoranges fail). ``predicted``: every row's
    pseudorange at ``centre`` when the caller has it."""
    probability = session.options["gate_probability"]
    if probability <= 0.0 or rows.size == 0:
        return rows, False
    residual, systems = range_residuals(session, centre, prs, known, std, rows, predicted)
    if predicted_cov is None:
        predicted_cov = session_covariance(session) + model.process_noise(dt)
    variance = std[rows] ** 2 + float(np.trace(predicted_cov[:3, :3]))
    for system, members in group_rows(systems).items():
        if len(members) >= 3:
            residual[members] -= median(residual[members])
        else:
            clock = layout.CLOCK[system]
            variance[members] += predicted_cov[clock, clock] if system in session.clock_seen else 1e12
    score = residual**2 / variance
    threshold = chi2_threshold(probability)
    failed = score > threshold
    if failed.sum() * 2 > rows.size and rows.size >= 4:
        return rows, True
    for r, value in zip(rows[failed], score[failed]):
        i = indices[r]
        uses[i] = MeasurementUse(
            i,
            "pseudorange",
            False,
            f"failed the residual test: {value:.1f} > {threshold:.1f} (chi-square, 1 dof)",
        )
    return rows[~failed], False


_THRESHOLDS: dict[tuple[float, int], float] = {}


def group_rows(groups: Sequence[str]) -> dict[str, list[int]]:
    """The positions of each group's rows, in order (what a boolean mask ``labels == group`` selects, and
    indexes an array the same way), found in one pass instead of a mask per group."""
    members: dict[str, list[int]] = {}
    for row, group in enumerate(groups):
        members.setdefault(group, []).append(row)
    return members


def median(values: np.ndarray) -> float:
    """np.median of a short 1-D array, the same value (the middle element, or the two middle ones' mean)
    without its general machinery: the screens take several medians of a few satellites every epoch."""
    ordered = np.sort(values)
    half = len(ordered) // 2
    if len(ordered) % 2:
        return float(ordered[half])
    return float((ordered[half - 1] + ordered[half]) / 2.0)


def chi2_threshold(probability: float, dof: int = 1) -> float:
    key = (probability, dof)
    if key not in _THRESHOLDS:
        _THRESHOLDS[key] = float(chi2.ppf(probability, dof))
    return _THRESHOLDS[key]


def left_out(rows: np.ndarray, kept: np.ndarray) -> list[int]:
    """The rows (ascending) not in ``kept``: np.setdiff1d's answer for a handful of rows, without its sorts."""
    keep = set(kept.tolist())
    return [r for r in rows.tolist() if r not in keep]
