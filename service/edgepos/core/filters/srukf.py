"""Square-root unscented Kalman filter (van der Merwe & Wan 2001), as the V2X/GPS/DR paper's DR and
V2X sub-filters use it (its ref. [4]).

Same sigma points and weights as :class:`UnscentedKalmanFilter`; the difference is how second
moments are formed: never as sums of outer products, but as the triangular factor of a QR
decomposition of the weighted deviations stacked over a square root of the noise, followed by a
rank-one Cholesky update (or downdate, when the centre weight is negative) for the centre point.
That keeps every covariance the filter forms positive semidefinite by construction.

Sessions store covariances (plain data shared with every other filter), so the state's factor is
taken afresh from the stored covariance at each step; predicted covariances and innovation
covariances come out of the square-root recursions and are returned as S S^T to keep the common
predict/update contract. In exact arithmetic every result equals the UKF's.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from edgepos.core import layout
from edgepos.core.errors import NumericalError
from edgepos.core.filters.ukf import UnscentedKalmanFilter
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.motion.base import MotionModel
from edgepos.core.numerics import (
    FloatArray,
    require_finite,
    robust_cholesky,
    weighted_mean,
    wrap_angle,
    wrap_rows,
)


def noise_square_root(noise: np.ndarray) -> np.ndarray:
    """Rows A with A^T A = ``noise`` for a symmetric positive semidefinite matrix (singular allowed:
    process noise often is). Built from the eigen-decomposition, so it is exact to rounding."""
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (noise + noise.T))
    scale = max(float(np.max(np.abs(eigenvalues))), 1e-300)
    if eigenvalues.min() < -1e-9 * scale:
        raise NumericalError(f"noise covariance is indefinite (smallest eigenvalue {eigenvalues.min():.3g})")
    rows: FloatArray = np.sqrt(np.maximum(eigenvalues, 0.0))[:, None] * eigenvectors.T
    return rows


def cholesky_update(upper: np.ndarray, vector: np.ndarray, sign: float) -> np.ndarray:
    """Upper factor R' with R'^T R' = R^T R + sign * v v^T (sign +1 update, -1 downdate).

    A downdate that would make the matrix indefinite raises :class:`NumericalError`."""
    factor = upper.copy()
    v = vector.astype(float).copy()
    for k in range(v.size):
        diagonal = factor[k, k]
        squared = diagonal * diagonal + sign * v[k] * v[k]
        if not squared > 0.0:
            if squared == 0.0 and v[k] == 0.0:
                continue
            raise NumericalError("square-root covariance downdate lost positive definiteness")
        root = np.sqrt(squared)
        if diagonal == 0.0:  # rank-deficient factor: form the matrix once instead
            full = upper.T @ upper + sign * np.outer(vector, vector)
            return robust_cholesky(0.5 * (full + full.T)).T
        cosine, sine = root / diagonal, v[k] / diagonal
        factor[k, k] = root
        factor[k, k + 1 :] = (factor[k, k + 1 :] + sign * sine * v[k + 1 :]) / cosine
        v[k + 1 :] = cosine * v[k + 1 :] - sine * factor[k, k + 1 :]
    return factor


def triangular_factor(rows: np.ndarray, centre: np.ndarray | None, centre_weight: float) -> np.ndarray:
    """Upper R with R^T R = rows^T rows + centre_weight * centre centre^T (QR, then rank-one step)."""
    # numpy's stubs type every mode of qr as QRResult; mode "r" returns the factor R alone.
    upper = cast(FloatArray, np.linalg.qr(rows, mode="r"))
    upper = upper * np.where(np.diag(upper) < 0.0, -1.0, 1.0)[:, None]  # non-negative diagonal
    dim = rows.shape[1]
    if upper.shape[0] < dim:
        upper = np.vstack([upper, np.zeros((dim - upper.shape[0], dim))])
    if centre is not None and centre_weight != 0.0:
        upper = cholesky_update(
            upper, np.sqrt(abs(centre_weight)) * centre, 1.0 if centre_weight > 0 else -1.0
        )
    return upper


class SquareRootUnscentedKalmanFilter(UnscentedKalmanFilter):
    """The UKF's moments through square-root (QR + Cholesky update) recursions."""

    name = "srukf"

    def predict(
        self, mean: np.ndarray, cov: np.ndarray, motion: MotionModel, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        noise_rows = noise_square_root(motion.noise_covariance(mean, dt))
        mask = layout.angle_mask(motion.components)
        factor = robust_cholesky(cov)
        if motion.linear:
            transition = motion.transition_matrix(mean, dt)
            new_mean = wrap_rows(transition @ mean, mask)
            upper = triangular_factor(np.vstack([factor.T @ transition.T, noise_rows]), None, 0.0)
        else:
            offsets, mean_weights, cov_weights = self.unit_points(mean.size)
            moved = motion.propagate(mean + offsets @ factor.T, dt)
            new_mean = weighted_mean(moved, mean_weights, mask)
            deviations = wrap_rows(moved - new_mean, mask)
            upper = _weighted_factor(deviations, cov_weights, noise_rows, self.has_centre_point)
        new_cov = upper.T @ upper
        new_cov = 0.5 * (new_cov + new_cov.T)
        require_finite("predicted state", new_mean, new_cov)
        return new_mean, new_cov

    def measurement_moments(
        self, means: np.ndarray, covs: np.ndarray, active: np.ndarray, measurement: MeasurementModel
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        offsets, mean_weights, cov_weights = self.bank_points(means, covs, active)
        count, points = offsets.shape[:2]
        z = measurement.predict((means[:, None, :] + offsets).reshape(count * points, -1)).reshape(
            count, points, -1
        )
        predicted = (mean_weights[:, None, :] @ z)[:, 0, :]
        angles = measurement.angle_rows
        if angles.size:
            predicted[:, angles] = np.arctan2(
                (mean_weights[:, None, :] @ np.sin(z[:, :, angles]))[:, 0, :],
                (mean_weights[:, None, :] @ np.cos(z[:, :, angles]))[:, 0, :],
            )
        z_dev = z - predicted[:, None, :]
        if angles.size:
            z_dev[:, :, angles] = wrap_angle(z_dev[:, :, angles])
        noise_rows = noise_square_root(measurement.noise_covariance())
        innovation_cov = np.empty((count, measurement.dim, measurement.dim))
        for b in range(count):
            upper = _weighted_factor(z_dev[b], cov_weights[b], noise_rows, self.has_centre_point)
            innovation_cov[b] = upper.T @ upper
        cross_cov = offsets.transpose(0, 2, 1) @ (z_dev * cov_weights[:, :, None])
        return predicted, 0.5 * (innovation_cov + innovation_cov.transpose(0, 2, 1)), cross_cov


def _weighted_factor(
    deviations: np.ndarray, cov_weights: np.ndarray, noise_rows: np.ndarray, has_centre: bool
) -> np.ndarray:
    """Upper factor of sum_i w_i d_i d_i^T + noise: QR over the side points (non-negative weights)
    and the noise rows, then the centre point's rank-one update or downdate."""
    start = 1 if has_centre else 0
    side_weights = cov_weights[start:]
    if np.any(side_weights < 0.0):
        raise NumericalError("square-root UKF needs non-negative side-point weights")
    rows = np.vstack([np.sqrt(side_weights)[:, None] * deviations[start:], noise_rows])
    if has_centre:
        return triangular_factor(rows, deviations[0], float(cov_weights[0]))
    return triangular_factor(rows, None, 0.0)
