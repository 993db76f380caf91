"""The measurement-model contract: z = h(x) + v, v ~ N(0, R), evaluated on full 8-dim states.

Models see full-state rows so that one model serves every motion model; components a motion model
does not carry are zero there (``core.layout.embed``). Rows flagged in ``angle_mask`` are angles:
their residuals are wrapped and their sigma-point means are circular.
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from collections.abc import Sequence

import numpy as np

from edgepos.core.numerics import FloatArray, wrap_angle


class MeasurementModel(ABC):
    """One measurement block of known dimension, noise and angle rows."""

    @property
    @abstractmethod
    def dim(self) -> int:
        """Number of scalar measurements."""

    @property
    @abstractmethod
    def angle_mask(self) -> np.ndarray:
        """Boolean (dim,) flags of the rows that are angles in radians."""

    @abstractmethod
    def predict(self, states: np.ndarray) -> np.ndarray:
        """h applied to each full-state row of ``states`` (n, 8); returns (n, dim)."""

    @abstractmethod
    def jacobian(self, states: np.ndarray) -> np.ndarray:
        """dh/dx at each full-state row of ``states`` (n, 8); returns (n, dim, 8)."""

    @abstractmethod
    def noise_covariance(self) -> np.ndarray:
        """R, (dim, dim)."""

    @functools.cached_property
    def angle_rows(self) -> np.ndarray:
        """Indices of the angle rows (empty when there are none)."""
        return np.flatnonzero(self.angle_mask)

    def residual(self, observed: np.ndarray, predicted: np.ndarray) -> np.ndarray:
        """observed - predicted with angle rows wrapped to [-pi, pi)."""
        residual: FloatArray = np.asarray(observed, dtype=float) - predicted
        if self.angle_rows.size:
            residual[..., self.angle_rows] = wrap_angle(residual[..., self.angle_rows])
        return residual


class Stacked(MeasurementModel):
    """Several measurement blocks taken in one joint update (their noises are independent)."""

    def __init__(self, parts: Sequence[MeasurementModel]) -> None:
        if not parts:
            raise ValueError("a stacked measurement needs at least one part")
        self.parts = tuple(parts)
        self._mask = np.concatenate([part.angle_mask for part in self.parts])
        self._noise = np.zeros((self._mask.size, self._mask.size))
        start = 0
        for part in self.parts:
            end = start + part.dim
            self._noise[start:end, start:end] = part.noise_covariance()
            start = end

    @property
    def dim(self) -> int:
        return int(self._mask.size)

    @property
    def angle_mask(self) -> np.ndarray:
        return self._mask

    def predict(self, states: np.ndarray) -> np.ndarray:
        return np.concatenate([part.predict(states) for part in self.parts], axis=1)

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        return np.concatenate([part.jacobian(states) for part in self.parts], axis=1)

    def noise_covariance(self) -> np.ndarray:
        return self._noise
