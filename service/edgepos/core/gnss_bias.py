"""Time-correlated GNSS fix errors as first-order Gauss-Markov bias states beside a kinematic state.

A receiver's fix errors are not white: multipath, atmosphere and orbit errors drift over tens of
seconds (docs/v2v.md measures them on a real recording). A filter that takes each fix as independent
averages the same error again and again and claims a covariance many times too small. Here the fix
is z = p + b + v, v white, and each axis of b is b' = phi b + w with phi = exp(-dt / tau) and
var(w) = sigma^2 (1 - phi^2), which keeps b's stationary variance sigma^2 at any step.

The bias is kept beside the kinematic filter's own (mean, cov) as a :class:`Bias` block (its mean,
covariance and cross-covariance with the kinematic state), so every existing filter and measurement
model keeps running on the kinematic state alone: after any update that does not measure b (dead
reckoning, ranges) :func:`condition` carries its effect over to b exactly for a linear update (the
Gaussian's conditional b | kinematic is unchanged by information about the kinematic state alone),
and :func:`predict` / :func:`fix_update` handle what involves b. ``sigma = 0`` turns the bias off
(white fixes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edgepos.core.errors import NumericalError
from edgepos.core.numerics import require_finite, symmetrize

POSITION = (0, 3)
"""Indices of x and y in the kinematic state [xp, xv, xa, yp, yv, ya]."""


def discretise(tau: float, sigma: float, dt: float) -> tuple[float, float]:
    """(phi, q) of one axis over ``dt`` >= 0: b' = phi b + w, var(w) = q = sigma^2 (1 - phi^2)."""
    if tau <= 0.0 or sigma < 0.0 or dt < 0.0:
        raise ValueError(f"need tau > 0, sigma >= 0, dt >= 0; got {tau}, {sigma}, {dt}")
    phi = math.exp(-dt / tau)
    return phi, sigma * sigma * (1.0 - phi * phi)


@dataclass
class Bias:
    """The (x, y) bias's mean (2,), covariance (2, 2) and cross-covariance with the kinematic state (n, 2)."""

    mean: np.ndarray
    cov: np.ndarray
    cross: np.ndarray

    @classmethod
    def stationary(cls, sigma: float, dim: int = 6) -> Bias:
        """Zero mean with the stationary variance, uncorrelated with the kinematic state."""
        return cls(np.zeros(2), np.eye(2) * sigma * sigma, np.zeros((dim, 2)))

    def copy(self) -> Bias:
        return Bias(self.mean.copy(), self.cov.copy(), self.cross.copy())

    def arrays(self) -> np.ndarray:
        """The block as one (n + 3, 2) array (for the session store): mean, covariance, cross rows."""
        return np.vstack([self.mean[None, :], self.cov, self.cross])

    @classmethod
    def from_arrays(cls, block: np.ndarray) -> Bias:
        block = np.asarray(block, dtype=float)
        return cls(block[0].copy(), block[1:3].copy(), block[3:].copy())


def predict(bias: Bias, transition: np.ndarray, tau: float, sigma: float, dt: float) -> Bias:
    """The bias after ``dt``, beside a kinematic state predicted with the (linear) ``transition``."""
    phi, q = discretise(tau, sigma, dt)
    return Bias(
        phi * bias.mean, symmetrize(phi * phi * bias.cov + q * np.eye(2)), phi * (transition @ bias.cross)
    )


def condition(
    bias: Bias, prior_mean: np.ndarray, prior_cov: np.ndarray, mean: np.ndarray, cov: np.ndarray
) -> Bias:
    """The bias after the kinematic state went from (``prior_mean``, ``prior_cov``) to (``mean``, ``cov``)
    by a measurement of the kinematic state alone: b's regression on the state, G = C^T P^-1, carries the
    change (b += G dm, C = P' G^T, B -= G (P - P') G^T). Exact for a linear update."""
    if not np.any(bias.cross):
        return bias.copy()
    try:
        factor = np.linalg.cholesky(prior_cov)
    except np.linalg.LinAlgError:
        raise NumericalError(
            "prior covariance not positive definite when carrying an update to the GNSS bias"
        ) from None
    gain = np.linalg.solve(factor.T, np.linalg.solve(factor, bias.cross)).T  # (2, n)
    new = Bias(
        bias.mean + gain @ (mean - prior_mean),
        symmetrize(bias.cov - gain @ (prior_cov - cov) @ gain.T),
        cov @ gain.T,
    )
    require_finite("GNSS bias", new.mean, new.cov, new.cross)
    return new


def fix_update(
    mean: np.ndarray, cov: np.ndarray, bias: Bias, fix: np.ndarray, white_var: float
) -> tuple[np.ndarray, np.ndarray, Bias]:
    """Kalman update of the joint [kinematic, bias] with a fix z = p + b + v, var(v) = ``white_var`` per axis."""
    n = mean.size
    joint_mean = np.concatenate([mean, bias.mean])
    joint_cov = np.block([[cov, bias.cross], [bias.cross.T, bias.cov]])
    design = np.zeros((2, n + 2))
    design[0, POSITION[0]] = design[1, POSITION[1]] = 1.0
    design[:, n:] = np.eye(2)
    cross = joint_cov @ design.T
    innovation_cov = symmetrize(design @ cross + white_var * np.eye(2))
    try:
        factor = np.linalg.cholesky(innovation_cov)
    except np.linalg.LinAlgError:
        raise NumericalError("GNSS fix innovation covariance is not positive definite") from None
    gain = np.linalg.solve(factor.T, np.linalg.solve(factor, cross.T)).T
    joint_mean = joint_mean + gain @ (fix - design @ joint_mean)
    # Joseph form: stays positive semi-definite in floating point.
    keep = np.eye(n + 2) - gain @ design
    joint_cov = symmetrize(keep @ joint_cov @ keep.T + white_var * gain @ gain.T)
    require_finite("GNSS fix update", joint_mean, joint_cov)
    return joint_mean[:n], joint_cov[:n, :n], Bias(joint_mean[n:], joint_cov[n:, n:], joint_cov[:n, n:])


def white_variance(fix_std: float, sigma: float) -> float:
    """The white part of a fix's variance when its reported ``fix_std`` is the total 1-sigma per axis
    and ``sigma`` of it is the modelled bias: std^2 - sigma^2, at least a quarter of std^2 (a receiver
    reporting less than the bias model's size still has white noise; the model then over-covers)."""
    return max(fix_std * fix_std - sigma * sigma, 0.25 * fix_std * fix_std)
