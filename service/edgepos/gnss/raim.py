"""Solution-separation RAIM for a GNSS filter: one-satellite and one-constellation fault hypotheses, fault
detection and the horizontal protection level (pure numpy; docs/integrity.md, "GNSS (gnss_tight)").

Per epoch, linearised at the filter's prediction x^- (Blanch et al., "Baseline advanced RAIM user
algorithm", ION GNSS 2012; the prior as a pseudo-measurement as in Joerger and Pervan, "Kalman
filter-based integrity monitoring against sensor faults", JGCD 2013):

* Unknowns d = (north, east, up, one clock per constellation) (m) about x^-; the pseudoranges' prefit
  residuals z = rho - h(x^-) with Jacobian H and weights W = diag(1 / sigma^2); the prior's position
  information Lambda = (k P^-_pos)^-1 (k the covariance inflation); the clocks have no prior (a
  constellation's clock is whatever its satellites say).
* All-in-view: A_0 = H^T W H + Lambda, d_0 = A_0^-1 H^T W z, P_0 = A_0^-1. Hypothesis j (satellite j, or
  constellation c with its clock column) leaves its rows out: A_j, d_j, P_j the same way.
* Separation s_j = d_j - d_0 (horizontal), fault-free covariance S_j = P_j - P_0 (horizontal 2x2);
  test q_j = s_j^T S_j^-1 s_j against T^2, the chi-square (2 dof) quantile at P_FA / N.
* Protection level, from the filter's posterior horizontal covariance C (times k): the largest of
  R(k C, risk / 2) and, per hypothesis, T sqrt(lmax(S_j)) + R(k C + S_j, risk / 2 / N / p_j), R(C, p) the
  radius a 2-D Gaussian with covariance C exceeds with probability p (core.integrity.radial_bound) and p_j
  the hypothesis' prior fault probability.

Too few satellites (no redundancy without the prior: fewer than 3 + constellations + 1) leave the fault
unbounded except by the prior, which may already hold the fault: the epoch is ``unavailable``.

The hypotheses are computed by a compiled kernel (core/measurements/gnss_raim_kernel.py) unless
``EDGEPOS_NUMBA=0``; the numpy code here is its reference and decides every epoch the kernel declines.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.integrity import (
    ALARM,
    OK,
    UNAVAILABLE,
    Protection,
    radial_bound,
    radial_factor_table,
    test_threshold,
)
from edgepos.core.measurements.gnss_raim_kernel import hypothesis_bound_kernel
from edgepos.core.measurements.gnss_raim_kernel import separations as kernel_separations


@dataclass(frozen=True)
class RaimBudget:
    """The risks a GNSS protection level is sized to, per epoch."""

    integrity_risk: float
    false_alarm_probability: float
    satellite_fault_probability: float
    constellation_fault_probability: float
    alert_limit: float
    inflation: float
    """Factor k on the filter's covariances (prior and posterior): covers time-correlated range errors the
    filter treats as white."""


@dataclass(frozen=True)
class Separations:
    """One epoch's hypotheses: each one's rows left out, separation (east, north), its covariance S_j (2x2),
    test statistic sqrt(q_j) and prior fault probability; ``available`` False when the satellites cannot bound
    a fault."""

    available: bool
    hypotheses: tuple[tuple[tuple[int, ...], np.ndarray, np.ndarray, float, float], ...]
    threshold: float

    def worst(self, size: int | None = None) -> tuple[int, float] | None:
        """The failed hypothesis to exclude first (its index and sqrt(q)), None when every test passes: the
        satellite whose test fails most, or, when no satellite's fails, the constellation's (a satellite's
        fault also fails its constellation's test, by more). ``size`` 1: satellites only; >1: only
        constellations. Over all hypotheses it is found once per epoch's separations (the exclusion and the
        protection level both ask)."""
        if size is None:
            return self._worst_of_all
        return self._worst(size)

    @functools.cached_property
    def _worst_of_all(self) -> tuple[int, float] | None:
        return self._worst(None)

    def _worst(self, size: int | None) -> tuple[int, float] | None:
        best: tuple[int, float, int] | None = None
        for index, hypothesis in enumerate(self.hypotheses):
            statistic = hypothesis[3]
            single = len(hypothesis[0]) == 1
            if statistic <= self.threshold or (size is not None and single != (size == 1)):
                continue
            rank = 0 if single else 1
            if best is None or (rank, -statistic) < (best[2], -best[1]):
                best = (index, statistic, rank)
        return None if best is None else (best[0], best[1])


def _statistic(separation: np.ndarray, covariance: np.ndarray) -> float:
    """sqrt(s^T S^+ s): S's pseudo-inverse, since leaving one satellite out moves the solution along one
    direction only (S of rank 1); |s| <= sqrt(q lmax(S)) either way, which the protection level relies on."""
    values, vectors = np.linalg.eigh(covariance)
    keep = values > 1e-9 * max(float(values[-1]), 1e-300)
    projected = vectors[:, keep].T @ separation
    return math.sqrt(float(np.sum(projected**2 / values[keep])))


def _normal(
    h: np.ndarray, w: np.ndarray, prior: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The normal matrix's inverse with the rows ``keep`` and the position prior, and the state columns it
    has (position, then the clocks of the constellations left); None when it is not determined."""
    hk = h[keep]
    columns = np.concatenate([[0, 1, 2], np.flatnonzero(np.any(hk[:, 3:] != 0.0, axis=0)) + 3])
    hk = hk[:, columns]
    a = hk.T @ (w[keep, None] * hk)
    a[:3, :3] += prior
    try:
        cov = np.linalg.inv(a)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    return cov, columns


def _solve(
    h: np.ndarray, w: np.ndarray, z: np.ndarray, prior: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The weighted least-squares solution (east, north) and its 2x2 covariance with the rows ``keep`` and
    the position prior; None when it is not determined."""
    normal = _normal(h, w, prior, keep)
    if normal is None:
        return None
    cov, columns = normal
    d = cov @ (h[keep][:, columns].T @ (w[keep] * z[keep]))
    order = [1, 0]  # east, north
    return d[order], cov[np.ix_(order, order)]


def _constellation_solves(
    h: np.ndarray, w: np.ndarray, z: np.ndarray, prior: np.ndarray, systems: Sequence[str], groups: list[str]
) -> list[tuple[tuple[int, ...], np.ndarray, np.ndarray]] | None:
    """Each constellation's hypothesis: :func:`_solve` without its rows and its clock column, the normal
    matrices (all of one size: three position columns and the other constellations' clocks) inverted in one
    call. Per constellation its rows, solution (east, north) and 2x2 covariance; None when one is not
    determined."""
    labels = np.array(systems)
    normals: list[np.ndarray] = []
    rights: list[np.ndarray] = []
    row_sets: list[tuple[int, ...]] = []
    for group in groups:
        keep = labels != group
        hk = h[keep]
        # the columns _normal keeps: position, and the clocks some row left still has
        columns = np.concatenate([[0, 1, 2], np.flatnonzero(np.any(hk[:, 3:] != 0.0, axis=0)) + 3])
        if normals and len(columns) != len(normals[0]):  # clock columns not one per constellation
            return _each_solved(h, w, z, prior, labels, groups)
        hk = hk[:, columns]
        a = hk.T @ (w[keep, None] * hk)
        a[:3, :3] += prior
        normals.append(a)
        rights.append(hk.T @ (w[keep] * z[keep]))
        row_sets.append(tuple(np.flatnonzero(~keep).tolist()))
    try:
        covs = np.linalg.inv(np.array(normals))
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(covs)):
        return None
    order = [1, 0]  # east, north
    out = []
    for rows, cov, right in zip(row_sets, covs, rights):
        d = cov @ right
        out.append((rows, d[order], cov[np.ix_(order, order)]))
    return out


def _each_solved(
    h: np.ndarray, w: np.ndarray, z: np.ndarray, prior: np.ndarray, labels: np.ndarray, groups: list[str]
) -> list[tuple[tuple[int, ...], np.ndarray, np.ndarray]] | None:
    """:func:`_constellation_solves` one :func:`_solve` at a time, for a Jacobian whose normal matrices
    differ in size."""
    out = []
    for group in groups:
        keep = labels != group
        subset = _solve(h, w, z, prior, keep)
        if subset is None:
            return None
        out.append((tuple(np.flatnonzero(~keep).tolist()), subset[0], subset[1]))
    return out


def separations(
    h: np.ndarray,
    systems: Sequence[str],
    z: np.ndarray,
    std: np.ndarray,
    prior_position_cov: np.ndarray,
    budget: RaimBudget,
) -> Separations:
    """The hypotheses of one epoch: ``h`` (n x (3 + clocks)) the Jacobian of the pseudoranges with respect
    to (north, east, up, clocks), ``z`` their prefit residuals and ``std`` their noise std (m),
    ``prior_position_cov`` the filter's predicted (north, east, up) covariance (m^2).

    A satellite's hypothesis is the all-in-view solution's rank-one downdate (leave-one-out: separation
    -g w r / (1 - w s), covariance g g^T w / (1 - w s), g = P_0 h_j, s = h_j^T g, r the post-fit residual),
    all satellites at once; a constellation's, and a satellite that alone fixes its constellation's clock,
    are solved again without their rows."""
    n = len(z)
    groups = sorted(set(systems))
    if n < 3 + len(groups) + 1:
        return Separations(False, (), 0.0)
    w = 1.0 / np.asarray(std, float) ** 2
    try:
        prior = np.linalg.inv(budget.inflation * np.asarray(prior_position_cov, float))
    except np.linalg.LinAlgError:
        return Separations(False, (), 0.0)
    if compiled_enabled():
        compiled = _compiled_separations(h, systems, groups, z, w, prior, budget)
        if compiled is not None:
            return compiled
    every = np.ones(n, dtype=bool)
    normal = _normal(h, w, prior, every)
    if normal is None:
        return Separations(False, (), 0.0)
    p0, _ = normal
    d0 = p0 @ (h.T @ (w * z))
    order = [1, 0]  # east, north
    east_north_0 = d0[order]
    g = p0 @ h.T  # (states, n)
    s = np.einsum("ij,ji->i", h, g)
    denominator = 1.0 - w * s
    residual = z - h @ d0
    tests = n + (len(groups) if len(groups) > 1 else 0)
    threshold = test_threshold(budget.false_alarm_probability, tests)
    hypotheses: list[tuple[tuple[int, ...], np.ndarray, np.ndarray, float, float]] = []
    gh = g[order].T  # (n, 2)
    # every satellite's downdate at once (the same operations, row by row, as one satellite's)
    downdated = denominator > 1e-9
    scale = np.where(downdated, w / np.where(downdated, denominator, 1.0), 0.0)
    separation_all = -gh * scale[:, None] * residual[:, None]
    covariance_all = scale[:, None, None] * (gh[:, :, None] * gh[:, None, :])
    statistic_all = (np.abs(residual) * np.sqrt(scale)).tolist()
    p0_horizontal = p0[np.ix_(order, order)]
    for j in range(n):
        if downdated[j]:
            separation, covariance, statistic = separation_all[j], covariance_all[j], statistic_all[j]
        else:  # the constellation's only satellite: its clock goes with it
            keep = every.copy()
            keep[j] = False
            subset = _solve(h, w, z, prior, keep)
            if subset is None:
                return Separations(False, (), threshold)
            separation = subset[0] - east_north_0
            covariance = subset[1] - p0_horizontal
            covariance = 0.5 * (covariance + covariance.T)
            statistic = _statistic(separation, covariance)
        hypotheses.append(((j,), separation, covariance, statistic, budget.satellite_fault_probability))
    if len(groups) > 1:
        solved = _constellation_solves(h, w, z, prior, systems, groups)
        if solved is None:
            return Separations(False, (), threshold)
        for rows, east_north, subset_cov in solved:
            covariance = subset_cov - p0_horizontal
            covariance = 0.5 * (covariance + covariance.T)
            separation = east_north - east_north_0
            hypotheses.append(
                (
                    rows,
                    separation,
                    covariance,
                    _statistic(separation, covariance),
                    budget.constellation_fault_probability,
                )
            )
    return Separations(True, tuple(hypotheses), threshold)


def _compiled_separations(
    h: np.ndarray,
    systems: Sequence[str],
    groups: list[str],
    z: np.ndarray,
    w: np.ndarray,
    prior: np.ndarray,
    budget: RaimBudget,
) -> Separations | None:
    """:func:`separations` by the compiled kernel (core/measurements/gnss_raim_kernel.py), the same
    hypotheses in the same order; None when the kernel declines (a normal matrix not positive definite, a
    solution not finite), and the numpy form decides."""
    number = {system: k for k, system in enumerate(groups)}
    numbers = [number[s] for s in systems]
    group = np.array(numbers, dtype=np.int64)
    solved = kernel_separations(h, group, len(groups), z, w, prior)
    if solved is None:
        return None
    separation, covariance, statistic = solved
    n = len(z)
    tests = n + (len(groups) if len(groups) > 1 else 0)
    statistics = statistic.tolist()
    single = budget.satellite_fault_probability
    hypotheses: list[tuple[tuple[int, ...], np.ndarray, np.ndarray, float, float]] = [
        ((j,), separation[j], covariance[j], statistics[j], single) for j in range(n)
    ]
    if len(groups) > 1:
        for k in range(len(groups)):
            rows = tuple(j for j, g in enumerate(numbers) if g == k)
            hypotheses.append(
                (
                    rows,
                    separation[n + k],
                    covariance[n + k],
                    statistics[n + k],
                    budget.constellation_fault_probability,
                )
            )
    return Separations(True, tuple(hypotheses), test_threshold(budget.false_alarm_probability, tests))


def protection(separations_: Separations, fix_cov: np.ndarray, budget: RaimBudget) -> Protection:
    """The protection level of a fix with horizontal covariance ``fix_cov`` (east, north; m^2) and its
    state: ``alarm`` when a test fails or the level exceeds the alert limit."""
    if not separations_.available:
        return Protection(None, UNAVAILABLE)
    covariance = budget.inflation * np.asarray(fix_cov, float)
    covariance = 0.5 * (covariance + covariance.T)
    fault_free = 0.5 * budget.integrity_risk
    level = radial_bound(_matrix(covariance), fault_free)
    hypotheses = separations_.hypotheses
    if hypotheses:
        level = max(level, _hypothesis_bound(hypotheses, covariance, fault_free, separations_.threshold))
    if not math.isfinite(level):
        return Protection(None, UNAVAILABLE)
    worst = separations_.worst()
    if worst is not None:
        return Protection(level, ALARM, faulty=worst[0], statistic=worst[1], threshold=separations_.threshold)
    return Protection(level, ALARM if level > budget.alert_limit else OK)


def _hypothesis_bound(
    hypotheses: Sequence[tuple[tuple[int, ...], np.ndarray, np.ndarray, float, float]],
    covariance: np.ndarray,
    fault_free: float,
    threshold: float,
) -> float:
    """The largest over the hypotheses of T sqrt(lmax(S_j)) + R(k C + S_j, risk / 2 / N / p_j), all at once:
    :func:`core.integrity.radial_bound`'s formula on arrays, with its tables (``radial_factor_table``) per
    prior fault probability. NaN bounds are skipped, as the one-by-one maximum did. Computed by the compiled
    loop (``gnss_raim_kernel.hypothesis_bound_kernel``, the same bits) unless ``EDGEPOS_NUMBA=0`` or a
    value is not finite; the numpy form here is its reference."""
    separation_cov = np.array([hypothesis[2] for hypothesis in hypotheses])
    if compiled_enabled():
        bound = _compiled_hypothesis_bound(hypotheses, separation_cov, covariance, fault_free, threshold)
        if not math.isnan(bound):
            return bound
    a, b, d = separation_cov[:, 0, 0], separation_cov[:, 0, 1], separation_cov[:, 1, 1]
    largest = 0.5 * (a + d) + np.array(
        [math.hypot(x, y) for x, y in zip((0.5 * (a - d)).tolist(), b.tolist())]
    )
    bounds = threshold * np.sqrt(np.maximum(largest, 0.0))
    total = covariance + separation_cov
    a, b, d = total[:, 0, 0], total[:, 0, 1], total[:, 1, 1]
    half = 0.5 * (a - d)
    spread = np.sqrt(half * half + b * b)
    top = 0.5 * (a + d) + spread
    positive = top > 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.minimum(np.maximum((0.5 * (a + d) - spread) / np.where(positive, top, 1.0), 0.0), 1.0)
        root = np.sqrt(np.where(positive, top, 0.0))
    per_hypothesis = fault_free / len(hypotheses)
    probabilities = np.array([hypothesis[4] for hypothesis in hypotheses])
    radial = np.zeros(len(hypotheses))
    for probability in set(probabilities.tolist()):
        rows = (probabilities == probability) & positive
        table = radial_factor_table(per_hypothesis / probability)
        slot = np.ceil(ratio[rows] * (len(table) - 1) - 1e-12).astype(int)
        radial[rows] = table[slot] * root[rows]
    bounds = bounds + radial
    bounds = bounds[~np.isnan(bounds)]
    return float(bounds.max()) if bounds.size else -math.inf


def _compiled_hypothesis_bound(
    hypotheses: Sequence[tuple[tuple[int, ...], np.ndarray, np.ndarray, float, float]],
    separation_cov: np.ndarray,
    covariance: np.ndarray,
    fault_free: float,
    threshold: float,
) -> float:
    """:func:`_hypothesis_bound` by the kernel: lmax(S_j) with Python's ``math.hypot`` as the numpy form takes
    it, one radial factor table per prior fault probability; NaN when the kernel declines."""
    largest = np.array(
        [
            0.5 * (a + d) + math.hypot(0.5 * (a - d), b)
            for a, b, _, d in separation_cov.reshape(-1, 4).tolist()
        ]
    )
    per_hypothesis = fault_free / len(hypotheses)
    slots: dict[float, int] = {}
    table_of = np.array([slots.setdefault(h[4], len(slots)) for h in hypotheses], dtype=np.int64)
    tables = np.array([radial_factor_table(per_hypothesis / probability) for probability in slots])
    return float(
        hypothesis_bound_kernel(
            np.ascontiguousarray(separation_cov, dtype=float),
            largest,
            np.ascontiguousarray(covariance, dtype=float),
            float(threshold),
            table_of,
            tables,
        )
    )


def _matrix(m: np.ndarray) -> tuple[float, float, float]:
    return float(m[0, 0]), float(m[0, 1]), float(m[1, 1])
