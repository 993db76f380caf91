"""Corrections: how an epoch's measurements update a bank of priors.

``JointCorrection`` stacks every measurement into one update. ``AveragedCorrection`` is the RSU +
IMU paper's reading (sec. 2): one update per RSU (each with the shared gyro) from the same prior,
posteriors averaged; its model likelihood is the geometric mean of the per-RSU likelihoods, which
keeps it on the scale of a single update.

``RsuGyroEpoch`` holds one epoch's RSU range/bearing pairs and gyro readings as plain arrays: it
builds the correction for the numpy reference path, feeds the compiled kernels (``core.compiled``)
as is, and gives the Mahalanobis distances a gate needs.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.core import layout
from edgepos.core.filters.base import GaussianFilter, UpdateResult
from edgepos.core.imm import Correction, Gaussian
from edgepos.core.measurements import GyroYawRate, RsuRangeBearing, Stacked
from edgepos.core.measurements.base import MeasurementModel


class JointCorrection(Correction):
    """One update with ``measurement`` (possibly ``Stacked``) observed as ``observed``."""

    def __init__(self, measurement: MeasurementModel, observed: np.ndarray) -> None:
        self.measurement = measurement
        self.observed = np.asarray(observed, dtype=float)

    def apply(
        self, filt: GaussianFilter, means: np.ndarray, covs: np.ndarray, active: np.ndarray
    ) -> UpdateResult:
        return filt.update(means, covs, active, self.measurement, self.observed)


class AveragedCorrection(Correction):
    """Separate updates from the same priors, averaged (heading circularly)."""

    def __init__(self, parts: Sequence[JointCorrection]) -> None:
        if not parts:
            raise ValueError("an averaged correction needs at least one part")
        self.parts = tuple(parts)

    def apply(
        self, filt: GaussianFilter, means: np.ndarray, covs: np.ndarray, active: np.ndarray
    ) -> UpdateResult:
        results = [part.apply(filt, means, covs, active) for part in self.parts]
        if len(results) == 1:
            return results[0]
        stacked = np.stack([r.means for r in results])  # (K, B, 8)
        mean = stacked.mean(axis=0)
        heading = layout.PHI
        mean[:, heading] = np.arctan2(
            np.sin(stacked[:, :, heading]).mean(0), np.cos(stacked[:, :, heading]).mean(0)
        )
        mean[:, heading] *= active[:, heading]
        return UpdateResult(
            means=mean,
            covs=np.mean(np.stack([r.covs for r in results]), axis=0),
            nis=np.mean([r.nis for r in results], axis=0),
            log_likelihood=np.mean([r.log_likelihood for r in results], axis=0),
        )


#: The speed (m/s) at which the gyro model's squared speed is floored (its turn rate is undefined at rest).
GYRO_MIN_SPEED = 0.1


@dataclass(frozen=True)
class RsuGyroEpoch:
    """One epoch's RSU range/bearing pairs and gyro yaw rates, as plain arrays.

    ``positions`` (K, 2) RSU east/north (m), ``observed`` (K, 2) range (m) and bearing (rad, from the
    RSU to the vehicle), their noise standard deviations (K,) each, ``yaw_rates`` (G,) gyro readings
    (rad/s) with ``gyro_std``. ``averaged``: the paper's one update per RSU, averaged, instead of
    one joint update (only when K > 1; one RSU is the same either way).
    """

    positions: np.ndarray
    observed: np.ndarray
    range_std: np.ndarray
    bearing_std: np.ndarray
    yaw_rates: np.ndarray
    gyro_std: float
    averaged: bool = False
    gyro_min_speed: float = GYRO_MIN_SPEED

    @functools.cached_property
    def variances(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Range variances (K,), bearing variances (K,) and the gyro variance."""
        return np.square(self.range_std), np.square(self.bearing_std), self.gyro_std**2

    @functools.cached_property
    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """positions (K, 2), observed (K, 2), yaw rates (G,), range and bearing variances (K,) as
        contiguous float64, and the gyro variance: the compiled kernels' arguments (``core.compiled``),
        made once for the gate and the correction of an epoch."""
        range_variances, bearing_variances, gyro_variance = self.variances
        return (
            np.ascontiguousarray(self.positions, dtype=float),
            np.ascontiguousarray(self.observed, dtype=float),
            np.ascontiguousarray(self.yaw_rates, dtype=float),
            np.ascontiguousarray(range_variances, dtype=float),
            np.ascontiguousarray(bearing_variances, dtype=float),
            float(gyro_variance),
        )

    @property
    def rsu_count(self) -> int:
        return int(self.positions.shape[0])

    @property
    def dim(self) -> int:
        """Measurement dimension of one update: every pair stacked, or one pair when averaged."""
        return measurement_dim(self.rsu_count, int(self.yaw_rates.size), self.averaged)

    def measurement(
        self, rsus: Sequence[int] | None = None
    ) -> tuple[MeasurementModel, np.ndarray] | tuple[None, None]:
        """The stacked model [RSU pairs..., gyros...] of ``rsus`` (default all) and its observation;
        (None, None) when nothing was measured."""
        chosen = range(self.rsu_count) if rsus is None else rsus
        parts: list[MeasurementModel] = []
        observed = []
        if len(chosen):
            index = list(chosen)
            parts.append(
                RsuRangeBearing(self.positions[index], self.range_std[index], self.bearing_std[index])
            )
            observed.append(self.observed[index].ravel())
        if self.yaw_rates.size:
            parts.extend([GyroYawRate(self.gyro_std, self.gyro_min_speed)] * int(self.yaw_rates.size))
            observed.append(self.yaw_rates)
        if not parts:
            return None, None
        return (parts[0] if len(parts) == 1 else Stacked(parts)), np.concatenate(observed)

    def correction(self) -> Correction | None:
        """The correction of the numpy reference path, or None when nothing was measured."""
        if self.averaged and self.rsu_count > 1:
            corrections = []
            for k in range(self.rsu_count):
                model, observed = self.measurement([k])
                if model is not None and observed is not None:  # always: RSU k was measured
                    corrections.append(JointCorrection(model, observed))
            return AveragedCorrection(corrections)
        model, observed = self.measurement()
        return None if model is None or observed is None else JointCorrection(model, observed)


def measurement_dim(rsus: int, gyros: int, averaged: bool) -> int:
    """The measurement dimension of an epoch's update with ``rsus`` RSU pairs and ``gyros`` gyro readings:
    every pair stacked, or one pair when the pairs' updates are averaged."""
    return 2 * (1 if averaged and rsus > 1 else rsus) + gyros


def new_epoch(
    positions: np.ndarray,
    observed: np.ndarray,
    range_std: np.ndarray,
    bearing_std: np.ndarray,
    yaw_rates: np.ndarray,
    gyro_std: float,
    averaged: bool,
    range_variances: np.ndarray,
    bearing_variances: np.ndarray,
) -> RsuGyroEpoch:
    """``RsuGyroEpoch(...)`` (the default ``gyro_min_speed``) without the frozen ``__init__``, which sets
    its eight fields through ``object.__setattr__``, with its ``variances`` and ``kernel_arrays`` given:
    a pipeline that squared its batch's standard deviations once takes each epoch's rows of them.
    Every array must be contiguous float64 and the variances the squares of the standard deviations."""
    epoch = object.__new__(RsuGyroEpoch)
    gyro_variance = gyro_std**2
    epoch.__dict__.update(
        positions=positions,
        observed=observed,
        range_std=range_std,
        bearing_std=bearing_std,
        yaw_rates=yaw_rates,
        gyro_std=gyro_std,
        averaged=averaged,
        gyro_min_speed=GYRO_MIN_SPEED,
        variances=(range_variances, bearing_variances, gyro_variance),
        kernel_arrays=(
            positions,
            observed,
            yaw_rates,
            range_variances,
            bearing_variances,
            float(gyro_variance),
        ),
    )
    return epoch


def gate_distances(prior: Gaussian, epoch: RsuGyroEpoch) -> tuple[np.ndarray, np.ndarray]:
    """Squared Mahalanobis distances of each RSU pair (2 dof) and gyro reading (1 dof) from ``prior``.

    One linearisation at the prior mean; each group's distance uses its own diagonal block of
    S = H P H^T + R.
    """
    model, observed = epoch.measurement()
    if model is None or observed is None:  # nothing measured: no distances (as the compiled stepper)
        return np.empty(0), np.empty(0)
    idx = list(prior.components)
    mean = np.zeros(layout.FULL_DIM)
    mean[idx] = prior.mean
    jacobian = model.jacobian(mean[None, :])[0][:, idx]
    residual = model.residual(observed, model.predict(mean[None, :])[0])
    innovation_cov = jacobian @ prior.cov @ jacobian.T + model.noise_covariance()
    pairs = 2 * epoch.rsu_count
    diagonal, off_diagonal = np.diagonal(innovation_cov), np.diagonal(innovation_cov, 1)
    s11, s22, s12 = diagonal[0:pairs:2], diagonal[1:pairs:2], off_diagonal[0:pairs:2]  # 2x2 block per RSU
    r1, r2 = residual[0:pairs:2], residual[1:pairs:2]
    rsu_distance = (s22 * r1 * r1 - 2.0 * s12 * r1 * r2 + s11 * r2 * r2) / (s11 * s22 - s12 * s12)
    return rsu_distance, residual[pairs:] ** 2 / diagonal[pairs:]
