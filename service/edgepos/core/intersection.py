"""Covariance intersection: fusing estimates whose errors are correlated by an unknown amount.

A neighbour's published estimate and a vehicle's own both rest on GNSS fixes with a common error
(the same sky, the same atmosphere) and, after a few ranges, on each other. Treated as independent,
the same information counts twice and the covariance shrinks below the error. Covariance intersection
(Julier & Uhlmann 1997) is consistent whatever the correlation: for estimates with covariances P_i
(each an upper bound of its own error's), blockdiag(P_i / w_i) with w_i > 0, sum w_i = 1, bounds the
joint error covariance of any cross-correlation. The weights are chosen to minimise the trace of the
result's position covariance.
"""

from __future__ import annotations

import numpy as np

from edgepos.core.errors import NumericalError
from edgepos.core.numerics import symmetrize

WEIGHTS = np.concatenate([np.linspace(0.05, 0.95, 19), [1.0]])
"""The candidate own weights w: a grid fine enough that the trace is within a few percent of its
minimum (it is flat near it), and w = 1 (the other estimates unused) among them."""


def intersect(
    mean_a: np.ndarray, cov_a: np.ndarray, mean_b: np.ndarray | None, cov_b: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, float]:
    """CI of two estimates of the same state: P^-1 = w Pa^-1 + (1 - w) Pb^-1, x = P (w Pa^-1 xa +
    (1 - w) Pb^-1 xb), w in WEIGHTS minimising trace P. Without ``b`` (None): ``a`` itself, w = 1."""
    if mean_b is None or cov_b is None:
        return mean_a.copy(), cov_a.copy(), 1.0
    try:
        info_a, info_b = np.linalg.inv(cov_a), np.linalg.inv(cov_b)
    except np.linalg.LinAlgError:
        raise NumericalError("covariance intersection of a singular covariance") from None
    best = None
    for w in WEIGHTS:
        information = w * info_a + (1.0 - w) * info_b
        cov = symmetrize(np.linalg.inv(information))
        trace = float(np.trace(cov))
        if best is None or trace < best[0]:
            best = (trace, w, cov)
    assert best is not None
    _, w, cov = best
    mean = cov @ (w * info_a @ mean_a + (1.0 - w) * info_b @ mean_b)
    return mean, cov, float(w)


def range_weight(
    cov: np.ndarray,
    design: np.ndarray,
    neighbour_design: np.ndarray,
    neighbour_cov: np.ndarray,
    noise: np.ndarray,
    position: tuple[int, int],
    neighbours: int,
) -> float:
    """The own weight w for an update with measurements of the own state and ``neighbours`` other
    estimates, correlated by unknown amounts: the prior is taken as blockdiag(P / w, Pn (m / (1 - w)))
    (own state and each of the m neighbours weighted alike), and w in WEIGHTS minimises the trace of
    the linearised posterior's ``position`` block. ``design``: (k, n) Jacobian on the own state;
    ``neighbour_design``: (k, 2m) on the neighbours' stacked positions with joint covariance
    ``neighbour_cov`` (2m, 2m); ``noise``: (k, k). w = 1 means the measurements carry no weight."""
    idx = list(position)
    if neighbours == 0:
        return 1.0
    own = WEIGHTS[:-1]
    design_cov = design @ cov  # (k, n)
    own_term = design_cov @ design.T
    other = neighbour_design @ neighbour_cov @ neighbour_design.T
    innovation = (own_term[None] / own[:, None, None] + other[None] * (neighbours / (1.0 - own))[:, None, None]
                  + noise[None])
    cross = design_cov[:, idx].T  # (2, k)
    try:
        solved = np.linalg.solve(innovation, np.broadcast_to(cross.T, (own.size, *cross.T.shape)))  # (W, k, 2)
    except np.linalg.LinAlgError:
        raise NumericalError("innovation covariance of the intersected range update is singular") from None
    reduction = np.einsum("ik,wki->w", cross, solved) / (own * own)
    traces = np.trace(cov[np.ix_(idx, idx)]) / own - reduction
    best = int(np.argmin(traces))
    if traces[best] >= float(np.trace(cov[np.ix_(idx, idx)])):
        return 1.0
    return float(own[best])
