"""Covariance intersection: fusing estimates whose errors are correlated by an unknown amount.

A neighbour's published estimate and a vehicle's own both rest on GNSS fixes with a common error
(the same sky, the same atmosphere) and, after a few ranges, on each other. Treated as independent,
the same information counts twice and the covariance shrinks below the error. Covariance intersection
(Julier & Uhlmann 1997) is consistent whatever the correlation: for estimates with covariances P_i
(each an upper bound of its own error's), blockdiag(P_i / w_i) with w_i > 0, sum w_i = 1, bounds the
joint error covariance of any cross-correlation. The weights are chosen to minimise the result's
covariance: its trace for two estimates of one state, its determinant for a filter's range update.
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
    neighbours: int,
) -> float:
    """The own weight w for an update with measurements of the own state and ``neighbours`` other
    estimates, correlated by unknown amounts: the prior is taken as blockdiag(P / w, Pn (m / (1 - w)))
    (own state and each of the m neighbours weighted alike), and w in WEIGHTS minimises the determinant
    of the linearised posterior of the whole own state. By the determinant lemma, log det P+ = log det P
    - n log w + log det(S - H P H^T / w) - log det S, so no posterior is formed. (The trace of the
    position block alone is not enough: it lets a small w inflate what the measurements do not see,
    the velocity, every epoch, and a filter without another source of it diverges.)

    ``design``: (k, n) Jacobian on the own state; ``neighbour_design``: (k, 2m) on the neighbours'
    stacked positions with joint covariance ``neighbour_cov`` (2m, 2m); ``noise``: (k, k). w = 1 means
    the measurements carry no weight."""
    if neighbours == 0:
        return 1.0
    own = WEIGHTS[:-1]
    own_term = design @ cov @ design.T
    other = neighbour_design @ neighbour_cov @ neighbour_design.T
    rest = other[None] * (neighbours / (1.0 - own))[:, None, None] + noise[None]
    innovation = own_term[None] / own[:, None, None] + rest
    sign_rest, logdet_rest = np.linalg.slogdet(rest)
    sign_all, logdet_all = np.linalg.slogdet(innovation)
    if np.any(sign_rest <= 0) or np.any(sign_all <= 0):
        raise NumericalError("innovation covariance of the intersected range update is not positive definite")
    change = -cov.shape[0] * np.log(own) + logdet_rest - logdet_all
    best = int(np.argmin(change))
    return 1.0 if change[best] >= 0.0 else float(own[best])
