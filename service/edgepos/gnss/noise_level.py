"""An online estimate of how much larger the pseudorange errors are than the noise model says (the variance
scale s^2), from each epoch's own least-squares residuals. Pure numpy (scipy once per row count).

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import integrate, stats


@lru_cache(maxsize=128)
def expected_median(count: int) -> float:
    """E[median of ``count`` independent chi-square(1) samples] (for even counts the mean of the two middle
    order statistics): an order statistic's expectation, the integral of the chi-square quantile against the
    Beta density of its rank. 0.455 (the chi-square median) for large counts, 1 for one sample."""
    if count < 1:
        raise ValueError("count must be at least 1")

    def order_statistic(rank: int) -> float:
        density = stats.beta(rank, count - rank + 1).pdf
        value, _ = integrate.quad(lambda p: stats.chi2.ppf(p, 1) * density(p), 0.0, 1.0, limit=200)
        return float(value)

    if count % 2:
        return order_statistic(count // 2 + 1)
    return 0.5 * (order_statistic(count // 2) + order_statistic(count // 2 + 1))


def studentised_squares(jacobian: np.ndarray, residuals: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """u_i^2 of the weighted least-squares fit of ``residuals`` (prefit, rows of ``jacobian``) with weights
    1/``variance``: r_i^2 / (v_i (1 - h_ii)); empty when the rows do not exceed the unknowns."""
    rows, unknowns = jacobian.shape
    if rows <= unknowns:
        return np.zeros(0)
    weighted = jacobian / variance[:, None]
    try:
        normal_inverse = np.linalg.inv(jacobian.T @ weighted)
    except np.linalg.LinAlgError:
        return np.zeros(0)
    correction = normal_inverse @ (weighted.T @ residuals)
    post_fit = residuals - jacobian @ correction
    leverage = np.einsum("ij,jk,ik->i", weighted, normal_inverse, jacobian)
    remaining = 1.0 - leverage
    keep = remaining > 1e-9  # a row the fit must pass through says nothing about the noise
    value: np.ndarray = post_fit[keep] ** 2 / (variance[keep] * remaining[keep])
    return value


SNOOPING_SIGMA = 5.0
"""A row whose studentised residual exceeds this many times the epoch's median scale is left out and the
rest fitted again (one row per epoch, Baarda's data snooping: under a single fault the largest studentised
residual is the faulty row's). A clean row exceeds it with probability 6e-7."""


def epoch_scale(jacobian: np.ndarray, residuals: np.ndarray, variance: np.ndarray) -> tuple[float, int]:
    """(the epoch's median-based estimate of s^2, its redundancy rows - unknowns); (nan, 0) when the rows do
    not exceed the unknowns. A large fault on one row also moves the fit, and so every other row's residual
    (by its leverage on them): that row is left out first (:data:`SNOOPING_SIGMA`)."""
    rows, unknowns = jacobian.shape
    squares = studentised_squares(jacobian, residuals, variance)
    if squares.size == 0 or rows <= unknowns:
        return math.nan, 0
    estimate = float(np.median(squares)) / expected_median(int(squares.size))
    if rows - 1 <= unknowns or squares.size != rows:
        return estimate, rows - unknowns
    # the row with the largest studentised residual, tested against the fit of the others (its deleted
    # residual over that fit's scale), so that its own pull on the fit cannot hide it
    worst = int(np.argmax(squares))
    keep = np.arange(rows) != worst
    others = studentised_squares(jacobian[keep], residuals[keep], variance[keep])
    if others.size == 0:
        return estimate, rows - unknowns
    scale = float(np.median(others)) / expected_median(int(others.size))
    weighted = jacobian[keep] / variance[keep, None]
    try:
        normal_inverse = np.linalg.inv(jacobian[keep].T @ weighted)
    except np.linalg.LinAlgError:
        return estimate, rows - unknowns
    row = jacobian[worst]
    deleted = residuals[worst] - row @ (normal_inverse @ (weighted.T @ residuals[keep]))
    deleted_variance = variance[worst] + row @ normal_inverse @ row
    if deleted**2 / deleted_variance > SNOOPING_SIGMA**2 * scale:
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
