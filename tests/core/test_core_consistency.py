"""Filter consistency on a linear-Gaussian problem: NEES against its chi-square distribution.

Truth follows the CA model exactly (x_k = F x_{k-1} + w, w ~ N(0, Q)), measurements are positions
with white Gaussian noise, and the filters start from N(m0, P0) with x0 drawn from it. A consistent
filter's NEES at each step is chi-square with n = 6 dof, so the average over N runs times N is
chi-square with N n dof.
"""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.filters import CubatureKalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter
from edgepos.core.filters.base import GaussianFilter
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion import ConstantAcceleration
from scipy.stats import chi2

RUNS, STEPS, DT = 60, 40, 0.1


class PositionMeasurement(MeasurementModel):
    """z = (xp, yp) + v, v ~ N(0, std^2 I)."""

    def __init__(self, std: float) -> None:
        self.matrix = np.zeros((2, layout.FULL_DIM))
        self.matrix[0, layout.XP] = self.matrix[1, layout.YP] = 1.0
        self._noise = std**2 * np.eye(2)

    @property
    def dim(self) -> int:
        return 2

    @property
    def angle_mask(self) -> np.ndarray:
        return np.zeros(2, dtype=bool)

    def predict(self, states: np.ndarray) -> np.ndarray:
        return states @ self.matrix.T

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.matrix, (states.shape[0], 2, layout.FULL_DIM)).copy()

    def noise_covariance(self) -> np.ndarray:
        return self._noise


def nees_runs(filt: GaussianFilter, seed: int) -> np.ndarray:
    """NEES (runs, steps) of ``filt`` over Monte Carlo runs of the CA truth."""
    rng = np.random.default_rng(seed)
    motion = ConstantAcceleration(
        q=2.0, noise="continuous"
    )  # full-rank Q, so the truth can be drawn by Cholesky
    measurement = PositionMeasurement(std=0.8)
    transition = motion.transition_matrix(np.zeros(6), DT)
    noise_root = np.linalg.cholesky(motion.noise_covariance(np.zeros(6), DT))
    m0 = np.array([0.0, 10.0, 0.0, 0.0, 2.0, 0.0])
    p0 = np.diag([4.0, 1.0, 0.5, 4.0, 1.0, 0.5])
    p0_root = np.linalg.cholesky(p0)
    nees = np.empty((RUNS, STEPS))
    for run in range(RUNS):
        truth = m0 + p0_root @ rng.standard_normal(6)
        mean, cov = m0.copy(), p0.copy()
        for k in range(STEPS):
            truth = transition @ truth + noise_root @ rng.standard_normal(6)
            z = truth[[0, 3]] + rng.standard_normal(2) * 0.8
            mean, cov = filt.predict(mean, cov, motion, DT)
            mean, cov, _, _ = filt.update_one(mean, cov, motion.components, measurement, z)
            error = mean - truth
            nees[run, k] = error @ np.linalg.solve(cov, error)
    return nees


@pytest.mark.parametrize(
    "filt",
    [
        pytest.param(CubatureKalmanFilter(), id="ckf"),
        pytest.param(ExtendedKalmanFilter(), id="ekf"),
        pytest.param(UnscentedKalmanFilter(), id="ukf"),
    ],
)
def test_average_nees_is_inside_the_95_percent_chi_square_band(filt: GaussianFilter) -> None:
    nees = nees_runs(filt, seed=2025)
    dim = 6
    low, high = chi2.ppf([0.025, 0.975], RUNS * dim) / RUNS
    averaged = nees.mean(axis=0)  # per step, over runs
    # the final step (runs independent, so exactly chi-square N n / N if consistent)
    assert low <= averaged[-1] <= high, (
        f"final averaged NEES {averaged[-1]:.2f} outside [{low:.2f}, {high:.2f}]"
    )
    # per-step values are correlated in time but each should be in the band ~95 % of the time
    inside = np.mean((averaged >= low) & (averaged <= high))
    assert inside >= 0.85, f"only {inside:.0%} of steps inside [{low:.2f}, {high:.2f}]"
    # and the overall mean is close to the state dimension
    assert abs(nees.mean() - dim) < 0.5
