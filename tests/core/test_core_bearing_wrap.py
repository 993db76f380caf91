"""Bearings across the +-pi cut: circular predicted means, wrapped residuals, no 2 pi jumps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.filters import CubatureKalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter
from edgepos.core.filters.base import GaussianFilter, embed_bank
from edgepos.core.measurements import RsuRangeBearing
from edgepos.core.motion import ConstantAcceleration, ConstantVelocity
from edgepos.core.numerics import wrap_angle

FILTERS = [
    pytest.param(CubatureKalmanFilter(), id="ckf"),
    pytest.param(UnscentedKalmanFilter(), id="ukf"),
    pytest.param(UnscentedKalmanFilter(alpha=0.5, beta=2.0, kappa=0.0), id="ukf-a0.5"),
    pytest.param(ExtendedKalmanFilter(), id="ekf"),
]


def angular_distance(a: float, b: float) -> float:
    return abs(float(wrap_angle(a - b)))


@pytest.mark.parametrize("filt", FILTERS)
def test_tracking_through_the_bearing_cut_stays_accurate(filt: GaussianFilter) -> None:
    """The RSU stands east of the vehicle, which crosses the RSU's y: the bearing flips +pi <-> -pi."""
    rsu = np.array([[200.0, 0.0]])
    model = RsuRangeBearing(rsu, range_std=0.3, bearing_std=math.radians(0.2))
    motion = ConstantVelocity(q=0.05)
    rng = np.random.default_rng(31)
    dt, steps = 0.1, 100
    velocity = np.array([10.0, 2.0])
    start = np.array([0.0, -10.0])  # y crosses 0 at t = 5 s
    mean = np.array([start[0] + 0.5, velocity[0] - 0.3, start[1] - 0.5, velocity[1] + 0.2])
    cov = np.diag([1.0, 1.0, 1.0, 1.0])
    bearings = []
    for k in range(1, steps + 1):
        t = k * dt
        position = start + velocity * t
        full = np.zeros(8)
        full[[layout.XP, layout.YP]] = position
        z = model.predict(full[None, :])[0] + rng.standard_normal(2) * np.sqrt(
            np.diag(model.noise_covariance())
        )
        z[1] = wrap_angle(z[1])
        bearings.append(z[1])
        prior_mean, cov = filt.predict(mean, cov, motion, dt)
        mean, cov, nis, _ = filt.update_one(prior_mean, cov, motion.components, model, z)
        correction = np.hypot(mean[0] - prior_mean[0], mean[2] - prior_mean[2])
        assert correction < 2.0, f"step {k}: update moved the position by {correction:.1f} m"
        assert nis < 30.0, f"step {k}: NIS {nis:.1f}"
        if k > 10:
            error = np.hypot(mean[0] - position[0], mean[2] - position[1])
            assert error < 1.0, f"step {k}: position error {error:.2f} m"
    signs = np.sign(bearings)
    assert (signs > 0).any() and (signs < 0).any(), "the run must cross the bearing cut"
    assert min(abs(abs(b) - math.pi) for b in bearings) < 0.01


class RotatedBearing(RsuRangeBearing):
    """The same measurement with the bearing taken from the -x axis: atan2(-dy, -dx) = bearing - pi.

    Near bearing +-pi its values are near 0, so sigma points do not straddle the cut there.
    ``circular`` False treats the row as a plain number (arithmetic means).
    """

    def __init__(self, positions, range_std, bearing_std, circular: bool) -> None:
        super().__init__(positions, range_std, bearing_std)
        self.circular = circular

    def predict(self, states):
        out = super().predict(states)
        dx = states[:, layout.XP, None] - self.positions[:, 0]
        dy = states[:, layout.YP, None] - self.positions[:, 1]
        out[:, 1::2] = np.arctan2(-dy, -dx)
        return out

    @property
    def angle_mask(self):
        return super().angle_mask if self.circular else np.zeros(self.dim, dtype=bool)


def rotated_moments(filt: GaussianFilter, means, covs, active, rsu: np.ndarray, circular: bool):
    """Moments of the rotated measurement, with the bearing mean rotated back by pi."""
    rotated = RotatedBearing(rsu, 0.6, math.radians(0.5), circular)
    predicted, innovation_cov, cross_cov = filt.measurement_moments(means, covs, active, rotated)
    predicted = predicted.copy()
    predicted[:, 1] = wrap_angle(predicted[:, 1] + math.pi)
    return predicted, innovation_cov, cross_cov


@pytest.mark.parametrize("filt", FILTERS)
@pytest.mark.parametrize("y_offset", [0.0, 0.3, -0.7, 1e-12])
def test_predicted_bearing_is_a_circular_mean(filt: GaussianFilter, y_offset: float) -> None:
    """Sigma points straddle the cut (vehicle due west of the RSU, 2 m std across the line of sight)."""
    rsu = np.array([[0.0, 0.0]])
    model = RsuRangeBearing(rsu, 0.6, math.radians(0.5))
    rng = np.random.default_rng(41)
    root = rng.normal(0.0, 0.3, (6, 6))
    cov6 = root @ root.T + np.diag([1.0, 1.0, 0.1, 4.0, 1.0, 0.1])
    mean6 = np.array([-50.0, 3.0, 0.0, y_offset, -1.0, 0.0])
    means, covs, active = embed_bank([(mean6, cov6)], [ConstantAcceleration.components])
    predicted, innovation_cov, cross_cov = filt.measurement_moments(means, covs, active, model)
    # rotating the frame by pi commutes with the circular mean: same moments without any straddling
    ref_predicted, ref_innovation_cov, ref_cross_cov = rotated_moments(filt, means, covs, active, rsu, True)
    assert predicted[0, 0] == pytest.approx(ref_predicted[0, 0], rel=1e-12)
    assert angular_distance(predicted[0, 1], ref_predicted[0, 1]) < 1e-12
    # and it is close to the arithmetic mean of the continuous rotated angles (they differ at O(sigma^4))
    arithmetic, arithmetic_cov, _ = rotated_moments(filt, means, covs, active, rsu, False)
    assert angular_distance(predicted[0, 1], arithmetic[0, 1]) < 1e-6
    np.testing.assert_allclose(innovation_cov, arithmetic_cov, rtol=1e-5)
    assert abs(abs(predicted[0, 1]) - math.pi) < 0.05
    np.testing.assert_allclose(innovation_cov, ref_innovation_cov, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(cross_cov, ref_cross_cov, rtol=1e-9, atol=1e-12)
    # the bearing variance is (cross-range std / range)^2 + R, nowhere near pi^2
    assert innovation_cov[0, 1, 1] < 0.01


@pytest.mark.parametrize("filt", FILTERS)
def test_update_across_the_cut_uses_the_short_way_round(filt: GaussianFilter) -> None:
    rsu = np.array([[0.0, 0.0]])
    model = RsuRangeBearing(rsu, 0.6, math.radians(0.5))
    mean = np.array([-50.0, 3.0, 0.0, 0.2, -1.0, 0.0])  # bearing pi - 0.004
    cov = np.diag([1.0, 1.0, 0.1, 1.0, 1.0, 0.1])
    observed = np.array([50.0, -math.pi + 0.004])  # the mirror point, y = -0.2
    new_mean, new_cov, nis, _ = filt.update_one(mean, cov, ConstantAcceleration.components, model, observed)
    assert abs(new_mean[0] - -50.0) < 0.5
    assert -0.3 < new_mean[3] < 0.2  # pulled from 0.2 towards -0.2, not flung round the RSU
    assert nis < 5.0
    assert np.linalg.eigvalsh(new_cov).min() > 0.0


def test_residual_wraps_angle_rows_only() -> None:
    model = RsuRangeBearing(np.array([[0.0, 0.0], [5.0, 5.0]]), 0.6, 0.01)
    observed = np.array([10.0, -3.1, 20.0, 3.1])
    predicted = np.array([[10.5, 3.1, 19.0, -3.1]])
    residual = model.residual(observed, predicted)
    np.testing.assert_allclose(residual[0], [-0.5, 2 * math.pi - 6.2, 1.0, 6.2 - 2 * math.pi], atol=1e-12)


def test_ckf_bearing_moments_by_hand_across_the_cut() -> None:
    """The cubature sums of eqs. 20-24 written out, with a circular mean and wrapped deviations."""
    rsu = np.array([[0.0, 0.0]])
    model = RsuRangeBearing(rsu, 0.6, math.radians(0.5))
    mean = np.array([-40.0, 3.0, 0.0, 0.1, -1.0, 0.0])
    cov = np.diag([1.0, 1.0, 0.1, 9.0, 1.0, 0.1])
    cov[0, 3] = cov[3, 0] = 0.5
    dim = mean.size
    root = np.linalg.cholesky(cov)
    points = np.vstack(
        [mean + math.sqrt(dim) * root[:, i] for i in range(dim)]
        + [mean - math.sqrt(dim) * root[:, i] for i in range(dim)]
    )
    ranges = np.hypot(points[:, 0], points[:, 3])
    bearings = np.arctan2(points[:, 3], points[:, 0])
    assert (bearings > 3.0).any() and (bearings < -3.0).any()  # the points straddle the cut
    bearing_mean = math.atan2(np.mean(np.sin(bearings)), np.mean(np.cos(bearings)))
    deviations = np.column_stack([ranges - ranges.mean(), wrap_angle(bearings - bearing_mean)])
    expected_s = deviations.T @ deviations / (2 * dim) + model.noise_covariance()
    expected_c = (points - mean).T @ deviations / (2 * dim)
    means, covs, active = embed_bank([(mean, cov)], [ConstantAcceleration.components])
    predicted, innovation_cov, cross_cov = CubatureKalmanFilter().measurement_moments(
        means, covs, active, model
    )
    assert predicted[0, 0] == pytest.approx(ranges.mean(), rel=1e-13)
    assert angular_distance(predicted[0, 1], bearing_mean) < 1e-13
    np.testing.assert_allclose(innovation_cov[0], expected_s, rtol=1e-10)
    np.testing.assert_allclose(
        cross_cov[0][list(ConstantAcceleration.components)], expected_c, rtol=1e-10, atol=1e-13
    )
