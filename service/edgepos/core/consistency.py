"""An online estimate of how much larger a filter's state error is than its covariance says, from the
filter's own innovations of a measurement whose noise is known. Pure numpy and scipy's chi-square quantiles.

An update with innovation nu and innovation covariance S = A + R, A = H P H^T the predicted state's share
and R the measurement noise, has the normalised innovation squared e = nu^T S^-1 nu (m degrees of freedom).
If the state's error covariance is really s P (R known), E[e] = tr(S^-1 R) + s tr(S^-1 A) = (m - a) + s a
with a = tr(S^-1 A), the state's share of the innovation in S's own metric (0 to m). So s is estimated as

    s = sum(e - (m - a)) / sum(a)

over a memory: the scale for which the NIS summed over it is what the model predicts. The plain check, NIS
over its dof, would report 1 + (s - 1) a / m instead: where the measurement noise dominates S (a << m) it
barely moves however wrong P is. That is the cooperative pipelines' case on the papers' scenes: white 3.5 m
fixes against a filter that claims about 0.5 m, a / m about 0.03, NIS / dof 1.06-1.1 while the position's
NEES / dof is 3-6 (docs/integrity.md, "The fix's consistency scale"). The price is noise: one epoch's
(e - (m - a)) / a has a standard deviation of about sqrt(2 m) / a, so the memory must be long where a is
small, and a single epoch can say little.

Robust: each epoch's e is clipped at the (1 - CLIP_PROBABILITY) quantile of its distribution under the
current estimate (chi-square with m dof scaled by (m - a + s a) / m), so one outlier (a reflected fix) moves
the sums by a bounded amount. Memory: both sums decay with exp(-dt / T). What is reported is max(1, s): the
scale never claims the filter is better than its covariance says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import stats

from edgepos.core.gnss_bias import POSITION, Bias

CLIP_PROBABILITY = 1e-3
"""An epoch's NIS above its distribution's (1 - this) quantile under the current scale counts as that quantile."""


@lru_cache(maxsize=16)
def _quantile(dof: int) -> float:
    return float(stats.chi2.ppf(1.0 - CLIP_PROBABILITY, dof))


def innovation_terms(
    innovation: np.ndarray, state_part: np.ndarray, noise: np.ndarray
) -> tuple[float, float]:
    """(e, a) of one update: NIS e = nu^T S^-1 nu with S = ``state_part`` + ``noise``, and the state's share
    a = tr(S^-1 A). (nan, 0) when S is not positive definite."""
    total = state_part + noise
    try:
        factor = np.linalg.cholesky(0.5 * (total + total.T))
    except np.linalg.LinAlgError:
        return math.nan, 0.0
    whitened = np.linalg.solve(factor, innovation)
    root = np.linalg.solve(factor, state_part)
    share = float(np.trace(np.linalg.solve(factor, root.T)))
    return float(whitened @ whitened), share


def gnss_fix_terms(
    mean: np.ndarray, cov: np.ndarray, bias: Bias, fix: np.ndarray, white_var: float
) -> tuple[float, float]:
    """(e, a) of a GNSS fix z = p + b + v (var(v) = ``white_var`` per axis) against the predicted
    kinematic state (``mean``, ``cov``; position at indices 0 and 3) and the bias beside it: innovation
    z - p - b, state part cov(p + b) = P + B + C + C^T (C the position-bias cross-covariance). With a zero
    bias block (white fixes) it is the plain position update's."""
    index = list(POSITION)
    cross = bias.cross[index]
    state_part = cov[np.ix_(index, index)] + bias.cov + cross + cross.T
    innovation = fix - mean[index] - bias.mean
    return innovation_terms(innovation, state_part, white_var * np.eye(2))


@dataclass(frozen=True)
class ConsistencyScale:
    """The running sums: ``excess`` = sum of (e - (m - a)), ``share`` = sum of a, each decayed by
    exp(-dt / T) since, and the time (s) of the last update that added to them. ``t`` None: no history."""

    excess: float = 0.0
    share: float = 0.0
    t: float | None = None

    def updated(
        self, t: float, nis: float, dof: int, share: float, time_constant_s: float
    ) -> ConsistencyScale:
        """This memory decayed to ``t`` with one update's NIS ``nis`` (``dof`` degrees of freedom) and state
        share ``share`` added (clipped, see the module docstring); itself when the update says nothing
        (non-finite NIS, no state share)."""
        if not (math.isfinite(nis) and math.isfinite(share)) or share <= 0.0 or dof < 1:
            return self
        share = min(share, float(dof))
        expected = dof - share + self.scale * share
        clipped = min(nis, _quantile(dof) * expected / dof)
        decay = 1.0 if self.t is None else math.exp(-max(t - self.t, 0.0) / time_constant_s)
        return ConsistencyScale(decay * self.excess + clipped - (dof - share), decay * self.share + share, t)

    @property
    def estimate(self) -> float:
        """s, the factor the predicted covariance is too small by (1 without history)."""
        return self.excess / self.share if self.share > 0.0 else 1.0

    @property
    def scale(self) -> float:
        """The factor on the reported covariance: the estimate, never below 1."""
        return max(1.0, self.estimate)

    def to_list(self) -> list[float]:
        """Plain data for a session's state: [] without history."""
        return [] if self.t is None else [self.excess, self.share, self.t]

    @staticmethod
    def from_list(values: list[float] | None) -> ConsistencyScale:
        """Inverse of :meth:`to_list`; None or [] (a state written before the estimate) is no history."""
        if not values:
            return ConsistencyScale()
        if len(values) != 3:
            raise ValueError(f"a consistency scale is [excess, share, t], got {len(values)} numbers")
        excess, share, t = (float(v) for v in values)
        if not (math.isfinite(excess) and math.isfinite(share) and math.isfinite(t)) or share < 0.0:
            raise ValueError("a consistency scale's numbers must be finite, its share not negative")
        return ConsistencyScale(excess, share, t)


def scaled_position(cov: np.ndarray, index: tuple[int, ...], scale: float) -> np.ndarray:
    """``cov`` with the rows and columns ``index`` (the position's) times sqrt(``scale``): the position
    block times the scale, its correlations with the rest kept, the rest unchanged."""
    if scale == 1.0:
        return cov
    factor = np.ones(cov.shape[0])
    factor[list(index)] = math.sqrt(scale)
    out: np.ndarray = cov * factor[:, None] * factor[None, :]
    return out
