"""Corrections: how an epoch's measurements update a bank of priors.

``JointCorrection`` stacks every measurement into one update. ``AveragedCorrection`` is the RSU +
IMU paper's reading (sec. 2): one update per RSU (each with the shared gyro) from the same prior,
posteriors averaged; its model likelihood is the geometric mean of the per-RSU likelihoods, which
keeps it on the scale of a single update.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from edgepos.core import layout
from edgepos.core.filters.base import GaussianFilter, UpdateResult
from edgepos.core.imm import Correction
from edgepos.core.measurements.base import MeasurementModel


class JointCorrection(Correction):
    """One update with ``measurement`` (possibly ``Stacked``) observed as ``observed``."""

    def __init__(self, measurement: MeasurementModel, observed: np.ndarray) -> None:
        self.measurement = measurement
        self.observed = np.asarray(observed, dtype=float)

    def apply(self, filt: GaussianFilter, means: np.ndarray, covs: np.ndarray, active: np.ndarray) -> UpdateResult:
        return filt.update(means, covs, active, self.measurement, self.observed)


class AveragedCorrection(Correction):
    """Separate updates from the same priors, averaged (heading circularly)."""

    def __init__(self, parts: Sequence[JointCorrection]) -> None:
        if not parts:
            raise ValueError("an averaged correction needs at least one part")
        self.parts = tuple(parts)

    def apply(self, filt: GaussianFilter, means: np.ndarray, covs: np.ndarray, active: np.ndarray) -> UpdateResult:
        results = [part.apply(filt, means, covs, active) for part in self.parts]
        if len(results) == 1:
            return results[0]
        stacked = np.stack([r.means for r in results])  # (K, B, 8)
        mean = stacked.mean(axis=0)
        heading = layout.PHI
        mean[:, heading] = np.arctan2(np.sin(stacked[:, :, heading]).mean(0), np.cos(stacked[:, :, heading]).mean(0))
        mean[:, heading] *= active[:, heading]
        return UpdateResult(
            means=mean,
            covs=np.mean(np.stack([r.covs for r in results]), axis=0),
            nis=np.mean([r.nis for r in results], axis=0),
            log_likelihood=np.mean([r.log_likelihood for r in results], axis=0),
        )
