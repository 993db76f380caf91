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

Its uncertainty, and an upper confidence bound (``ConsistencyScale.upper``). With the true scale s the
innovation is N(0, R + s A), so e = z^T M z with z standard normal and M having the eigenvalues of
S^-1 (R + s A) = I + (s - 1) K, K = S^-1 A (eigenvalues in [0, 1), trace a): e is a weighted sum of m
chi-squares of 1 dof with mean tr(M) = m + (s - 1) a and variance

    var(e) = 2 tr(M^2) = 2 (m + 2 (s - 1) a + (s - 1)^2 b),  b = tr(K^2)

(exactly, not only for a scaled chi-square: with all m eigenvalues of K equal, b = a^2 / m and this is
2 (m - a + s a)^2 / m). The estimate is s^ = sum(w_i x_i) / sum(w_i a_i), x_i = e_i - (m_i - a_i), with
the memory's weights w_i = exp(-(t - t_i) / T); taking the epochs' innovations as independent (a
filter's innovations are white when its model holds; see the caveats below),

    var(s^ | s) = 2 (W + 2 (s - 1) A2 + (s - 1)^2 B2) / N^2,
    W = sum(w_i^2 m_i), A2 = sum(w_i^2 a_i), B2 = sum(w_i^2 b_i), N = sum(w_i a_i),

three more sums decaying with exp(-2 dt / T). The upper bound at confidence c inverts the one-sided
test: s_u is the largest s under which the observed s^ is not below s by more than z_c of its standard
deviation, s_u - s^ = z_c sd(s^ | s_u), z_c the standard normal's c quantile. Squared, a quadratic in
s_u - 1 whose larger root is the bound; when N^2 <= 2 z_c^2 B2 (too little information: even an
unbounded s would not make s^ improbable) the bound is infinite. The normal approximation is
conservative here: s^ is a positive sum of chi-squares, skewed to the right, so its lower tail (the one
the bound guards against: an estimate too low) is shorter than the normal's. Caveats, said in
docs/integrity.md: the clip makes s^ slightly low for a filter far too small (an epoch beyond its
99.9 % quantile counts as that quantile), and an over-confident filter's innovations are not exactly
white (correlated errors make the variance above an underestimate).
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
) -> tuple[float, float, float]:
    """(e, a, b) of one update: NIS e = nu^T S^-1 nu with S = ``state_part`` + ``noise``, the state's share
    a = tr(S^-1 A) and b = tr((S^-1 A)^2), which sizes e's variance. (nan, 0, 0) when S is not positive
    definite."""
    total = state_part + noise
    try:
        factor = np.linalg.cholesky(0.5 * (total + total.T))
    except np.linalg.LinAlgError:
        return math.nan, 0.0, 0.0
    whitened = np.linalg.solve(factor, innovation)
    root = np.linalg.solve(factor, state_part)
    whitened_state = np.linalg.solve(factor, root.T)  # L^-1 A L^-T: S^-1 A's eigenvalues, symmetric
    share = float(np.trace(whitened_state))
    square = float(np.sum(whitened_state * whitened_state.T))
    return float(whitened @ whitened), share, square


def gnss_fix_terms(
    mean: np.ndarray, cov: np.ndarray, bias: Bias, fix: np.ndarray, white_var: float
) -> tuple[float, float, float]:
    """(e, a, b) of a GNSS fix z = p + b + v (var(v) = ``white_var`` per axis) against the predicted
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
    """The running sums: ``excess`` = sum of w (e - (m - a)), ``share`` = sum of w a, with w = exp(-age / T),
    the time (s) of the last update that added to them (None: no history), and the sums with w^2 that
    size the estimate's variance: ``spread_dof`` = sum of w^2 m, ``spread_share`` = sum of w^2 a,
    ``spread_square`` = sum of w^2 b (see the module docstring)."""

    excess: float = 0.0
    share: float = 0.0
    t: float | None = None
    spread_dof: float = 0.0
    spread_share: float = 0.0
    spread_square: float = 0.0

    def updated(
        self, t: float, nis: float, dof: int, share: float, time_constant_s: float, *, square: float
    ) -> ConsistencyScale:
        """This memory decayed to ``t`` with one update's NIS ``nis`` (``dof`` degrees of freedom), state
        share ``share`` and ``square`` = tr((S^-1 A)^2) added (the NIS clipped, see the module docstring);
        itself when the update says nothing (non-finite NIS, no state share)."""
        if not (math.isfinite(nis) and math.isfinite(share) and math.isfinite(square)):
            return self
        if share <= 0.0 or dof < 1:
            return self
        share = min(share, float(dof))
        square = min(max(square, 0.0), share)  # K's eigenvalues lie in [0, 1]: b <= a
        expected = dof - share + self.scale * share
        clipped = min(nis, _quantile(dof) * expected / dof)
        decay = 1.0 if self.t is None else math.exp(-max(t - self.t, 0.0) / time_constant_s)
        decay2 = decay * decay
        return ConsistencyScale(
            decay * self.excess + clipped - (dof - share),
            decay * self.share + share,
            t,
            decay2 * self.spread_dof + dof,
            decay2 * self.spread_share + share,
            decay2 * self.spread_square + square,
        )

    @property
    def estimate(self) -> float:
        """s, the factor the predicted covariance is too small by (1 without history)."""
        return self.excess / self.share if self.share > 0.0 else 1.0

    @property
    def scale(self) -> float:
        """The factor on the reported covariance: the estimate, never below 1."""
        return max(1.0, self.estimate)

    def upper(self, confidence: float) -> float:
        """An upper bound of s at ``confidence`` (in (0.5, 1)): s^ exceeds it with probability at most
        1 - ``confidence`` (module docstring), never below :attr:`scale`; infinite without history or
        with too little information to bound it."""
        if not 0.5 < confidence < 1.0:
            raise ValueError(f"a confidence must lie in (0.5, 1), got {confidence}")
        if self.t is None or self.share <= 0.0:
            return math.inf
        z2 = _normal_quantile(confidence) ** 2
        n2 = self.share * self.share
        # (u - u^)^2 N^2 = 2 z^2 (W + 2 u A2 + u^2 B2) with u = s - 1: a u^2 - 2 h u + c = 0
        lead = n2 - 2.0 * z2 * self.spread_square
        if lead <= 0.0:
            return math.inf
        centre = self.estimate - 1.0
        half = centre * n2 + 2.0 * z2 * self.spread_share
        constant = centre * centre * n2 - 2.0 * z2 * self.spread_dof
        root = (half + math.sqrt(max(half * half - lead * constant, 0.0))) / lead
        return max(self.scale, 1.0 + root)

    def to_list(self) -> list[float]:
        """Plain data for a session's state: [] without history."""
        if self.t is None:
            return []
        return [self.excess, self.share, self.t, self.spread_dof, self.spread_share, self.spread_square]

    @staticmethod
    def from_list(values: list[float] | None) -> ConsistencyScale:
        """Inverse of :meth:`to_list`; None or [] (a state written before the estimate) is no history; three
        numbers (written before the bound) are the estimate's sums without the spread's (zero: such a
        session's options keep the protection level on the estimate, ``consistency_bound`` false)."""
        if not values:
            return ConsistencyScale()
        if len(values) not in (3, 6):
            raise ValueError(
                "a consistency scale is [excess, share, t, spread_dof, spread_share, spread_square], "
                f"got {len(values)} numbers"
            )
        numbers = [float(v) for v in values]
        if (
            not all(math.isfinite(v) for v in numbers)
            or numbers[1] < 0.0
            or min(numbers[3:], default=0.0) < 0.0
        ):
            raise ValueError(
                "a consistency scale's numbers must be finite, its share and spreads not negative"
            )
        excess, share, t, *spread = numbers
        return ConsistencyScale(excess, share, t, *spread)


@lru_cache(maxsize=16)
def _normal_quantile(confidence: float) -> float:
    return float(stats.norm.ppf(confidence))


def scaled_position(cov: np.ndarray, index: tuple[int, ...], scale: float) -> np.ndarray:
    """``cov`` with the rows and columns ``index`` (the position's) times sqrt(``scale``): the position
    block times the scale, its correlations with the rest kept, the rest unchanged."""
    if scale == 1.0:
        return cov
    factor = np.ones(cov.shape[0])
    factor[list(index)] = math.sqrt(scale)
    out: np.ndarray = cov * factor[:, None] * factor[None, :]
    return out
