"""An online estimate of how much larger the pseudorange errors are than the noise model says (the variance
scale s^2), from each epoch's own least-squares residuals. Pure numpy and scipy's chi-square quantiles.

Per epoch: the weighted least-squares fit of the update's rows (Jacobian H by position and one clock per
constellation, each row weighted by 1 / its model variance v_i) leaves residuals r; the studentised ones,
u_i^2 = r_i^2 / (v_i (1 - h_ii)) with h_ii the fit's leverage, each have expectation s^2 whatever the
geometry (the leverages sum to the unknowns, which is how the fit's lost degrees of freedom are counted).
The epoch's estimate is the median of the u_i^2 over the expected median of as many chi-square(1) samples:
one reflected satellite moves a median by one rank, not by its square (and when it is large enough to drag
the fit, it is left out first: data snooping). Over time the estimates are averaged
with exponential memory of time constant T, each epoch weighted by its redundancy (rows - unknowns): the
errors are correlated over about a minute (gnss/error_correlation.py), so an estimate needs several
correlation times of data to mean anything, and T sets how fast it follows a street that changes.
What is reported is max(1, estimate): the level never claims the errors are smaller than the model's.

The per-epoch fit runs as a compiled kernel (core/measurements/gnss_noise_kernel.py) unless
``EDGEPOS_NUMBA=0``; :func:`epoch_scale`'s numpy form is its reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import special, stats

from edgepos.core.compiled import compiled_enabled
from edgepos.core.measurements.gnss_noise_kernel import epoch_medians

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(200)
_P = 0.5 * (_NODES + 1.0)
_W = 0.5 * _WEIGHTS
_QUANTILES = stats.chi2.ppf(_P, 1)
"""Gauss-Legendre nodes on (0, 1) and the chi-square(1) quantiles there: 200 nodes reproduce the adaptive
quadrature of the order statistics' expectations to 3e-9 for 3 to 60 samples, in 30 us instead of 20 ms
(a row count the process has not seen must not stall an epoch)."""


@lru_cache(maxsize=256)
def expected_median(count: int) -> float:
    """E[median of ``count`` independent chi-square(1) samples] (for even counts the mean of the two middle
    order statistics): an order statistic's expectation, the integral of the chi-square quantile against the
    Beta density of its rank. 1 for one or two samples (their mean), 0.455 (the chi-square median) for many."""
    if count < 1:
        raise ValueError("count must be at least 1")
    if count <= 2:
        return 1.0

    def order_statistic(rank: int) -> float:
        log_density = (
            (rank - 1) * np.log(_P) + (count - rank) * np.log1p(-_P) - special.betaln(rank, count - rank + 1)
        )
        return float(np.sum(_W * _QUANTILES * np.exp(log_density)))

    if count % 2:
        return order_statistic(count // 2 + 1)
    return 0.5 * (order_statistic(count // 2) + order_statistic(count // 2 + 1))


def _fit(
    jacobian: np.ndarray, residuals: np.ndarray, variance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(post-fit residuals, leverages h_ii, (H'WH)^-1) of the weighted least-squares fit; None when the rows
    do not exceed the unknowns or the geometry is singular."""
    rows, unknowns = jacobian.shape
    if rows <= unknowns:
        return None
    weighted = jacobian / variance[:, None]
    try:
        normal_inverse = np.linalg.inv(jacobian.T @ weighted)
    except np.linalg.LinAlgError:
        return None
    post_fit = residuals - jacobian @ (normal_inverse @ (weighted.T @ residuals))
    leverage = np.einsum("ij,jk,ik->i", weighted, normal_inverse, jacobian)
    return post_fit, leverage, normal_inverse


def _squares(post_fit: np.ndarray, leverage: np.ndarray, variance: np.ndarray) -> np.ndarray:
    remaining = 1.0 - leverage
    keep = remaining > 1e-9  # a row the fit must pass through says nothing about the noise
    value: np.ndarray = post_fit[keep] ** 2 / (variance[keep] * remaining[keep])
    return value


def studentised_squares(jacobian: np.ndarray, residuals: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """u_i^2 of the weighted least-squares fit of ``residuals`` (prefit, rows of ``jacobian``) with weights
    1/``variance``: r_i^2 / (v_i (1 - h_ii)); empty when the rows do not exceed the unknowns."""
    fit = _fit(jacobian, residuals, variance)
    return np.zeros(0) if fit is None else _squares(fit[0], fit[1], variance)


def _scale(squares: np.ndarray) -> float:
    return float(np.median(squares)) / expected_median(int(squares.size))


SNOOPING_SIGMA = 5.0
"""The row with the largest studentised residual is left out when that residual exceeds this many times
the scale of the other rows' fit (one row per epoch, Baarda's data snooping: under a single fault the
largest studentised residual is the faulty row's, and a fault large enough to drag the fit also inflates
the other rows' residuals, so it is judged against the fit without it). A clean row exceeds 5 sigma with
probability 6e-7."""


def epoch_scale(jacobian: np.ndarray, residuals: np.ndarray, variance: np.ndarray) -> tuple[float, int]:
    """(the epoch's median-based estimate of s^2, its redundancy rows - unknowns); (nan, 0) when the rows do
    not exceed the unknowns. The fit without the worst row comes from the full one by a rank-one downdate:
    with c = H A h_i (A = (H'WH)^-1), the others' residuals become r + c w_i r_i / (1 - h_ii) and their
    leverages h_jj + w_j c_j^2 w_i / (1 - h_ii); the left-out row's deleted residual r_i / (1 - h_ii) has
    variance v_i / (1 - h_ii), so its test statistic is its studentised square u_i^2."""
    rows, unknowns = jacobian.shape
    if rows > unknowns and compiled_enabled():
        medians = epoch_medians(jacobian, residuals, variance)
        if medians is not None:  # the compiled fit (None: the numpy form below decides)
            median, count, others_median, others_count, worst_square = medians
            if count == 0:
                return math.nan, 0
            estimate = median / expected_median(count)
            if others_count == 0:
                return estimate, rows - unknowns
            scale = others_median / expected_median(others_count)
            if worst_square > SNOOPING_SIGMA**2 * scale:
                return scale, rows - 1 - unknowns
            return estimate, rows - unknowns
    fit = _fit(jacobian, residuals, variance)
    if fit is None:
        return math.nan, 0
    post_fit, leverage, normal_inverse = fit
    squares = _squares(post_fit, leverage, variance)
    if squares.size == 0:
        return math.nan, 0
    estimate = _scale(squares)
    if rows - 1 <= unknowns or squares.size != rows:
        return estimate, rows - unknowns
    worst = int(np.argmax(squares))
    remaining = 1.0 - leverage[worst]
    coupling = jacobian @ (normal_inverse @ jacobian[worst])
    pull = coupling / (variance[worst] * remaining)
    keep = np.arange(rows) != worst
    others = _squares(
        (post_fit + pull * post_fit[worst])[keep],
        (leverage + coupling * pull / variance)[keep],
        variance[keep],
    )
    if others.size == 0:
        return estimate, rows - unknowns
    scale = _scale(others)
    if squares[worst] > SNOOPING_SIGMA**2 * scale:
        return scale, rows - 1 - unknowns
    return estimate, rows - unknowns


@dataclass(frozen=True)
class NoiseLevel:
    """The running estimate: the redundancy-weighted sum of the epochs' estimates and of their weights, each
    decayed by exp(-dt / T) since, and the time (s) of the last epoch that added to them. ``t`` None: no
    history yet."""

    total: float = 0.0
    weight: float = 0.0
    t: float | None = None

    def updated(self, t: float, estimate: float, redundancy: int, time_constant_s: float) -> NoiseLevel:
        """This memory decayed to ``t`` with the epoch's ``estimate`` (weight ``redundancy``) added; itself
        when the epoch has none."""
        if redundancy <= 0 or not math.isfinite(estimate):
            return self
        decay = 1.0 if self.t is None else math.exp(-max(t - self.t, 0.0) / time_constant_s)
        return NoiseLevel(decay * self.total + redundancy * estimate, decay * self.weight + redundancy, t)

    @property
    def estimate(self) -> float:
        """The variance scale the memory holds (1 without history)."""
        return self.total / self.weight if self.weight > 0.0 else 1.0

    @property
    def scale(self) -> float:
        """The factor on the reported covariance: the estimate, never below 1."""
        return max(1.0, self.estimate)

    def to_list(self) -> list[float]:
        """Plain data for a session's state: [] without history."""
        return [] if self.t is None else [self.total, self.weight, self.t]

    @staticmethod
    def from_list(values: list[float] | None) -> NoiseLevel:
        """Inverse of :meth:`to_list`; None or [] (a state written before the estimate) is no history."""
        if not values:
            return NoiseLevel()
        if len(values) != 3:
            raise ValueError(f"a noise level is [total, weight, t], got {len(values)} numbers")
        total, weight, t = (float(v) for v in values)
        if not (math.isfinite(total) and math.isfinite(weight) and math.isfinite(t)) or weight < 0.0:
            raise ValueError("a noise level's numbers must be finite, its weight not negative")
        return NoiseLevel(total, weight, t)
