"""Pseudorange observation model of the tightly coupled pipeline (Jiang & Chen 2018, eq. 7).

rho_i = |r_sat,i - r(x)| + Sagnac term + b_sys(i) + known_i, where r(x) is the receiver's ECEF position
from the state's geodetic offsets, r_sat,i the satellite's ECEF position at transmit time, b_sys the
receiver clock bias of the satellite's constellation (m) and ``known_i`` the terms computed once per epoch
at the predicted position: ionosphere + troposphere - c * satellite clock. Vectorised over any leading
axes of the states (particles, sigma points).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from edgepos.core.motion.riss import CLOCK, GeodeticAnchor
from edgepos.core.numerics import FloatArray
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT


@dataclass(frozen=True)
class PseudorangeModel:
    """m pseudoranges: satellite positions (m, 3) ECEF at transmit time, their systems' clock-bias state
    indices (m,), known additive terms (m,) in metres and noise standard deviations (m,) in metres."""

    anchor: GeodeticAnchor
    sat_position: np.ndarray
    clock_index: np.ndarray
    known_m: np.ndarray
    std_m: np.ndarray

    @classmethod
    def build(
        cls,
        anchor: GeodeticAnchor,
        sat_position: np.ndarray,
        systems: list[str] | tuple[str, ...],
        known_m: np.ndarray,
        std_m: np.ndarray,
    ) -> PseudorangeModel:
        return cls(
            anchor,
            np.asarray(sat_position, float),
            np.array([CLOCK[s] for s in systems], dtype=int),
            np.asarray(known_m, float),
            np.asarray(std_m, float),
        )

    @property
    def dim(self) -> int:
        return len(self.known_m)

    def predict(self, states: np.ndarray) -> np.ndarray:
        """Predicted pseudoranges (..., m) of states (..., DIM)."""
        return self.predict_at(states, self.anchor.ecef(states))

    def predict_at(self, states: np.ndarray, receiver: np.ndarray) -> np.ndarray:
        """:meth:`predict` with the states' ECEF positions (..., 3) already computed (shared with the
        range-rate model when both are updated together)."""
        square, turn = self._geometry
        # orbits.sagnac_range written as matrix products with the satellites' (3, m) columns, so that the
        # states x satellites terms need no (..., m, 3) temporaries: |s - r|^2 = |s|^2 - 2 r.s + |r|^2 (the
        # cancellation costs 1e-8 m of range) and the Sagnac term omega (x_s y_r - y_s x_r) / c = r . turn.
        distance = np.sqrt(
            np.maximum(
                square
                - 2.0 * (receiver @ self.sat_position.T)
                + np.sum(receiver * receiver, axis=-1)[..., None],
                0.0,
            )
        )
        pseudoranges: FloatArray = distance + receiver @ turn.T + states[..., self.clock_index] + self.known_m
        return pseudoranges

    @functools.cached_property
    def _geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """|s|^2 (m,) and the Sagnac term's rows (m, 3), computed once per model."""
        s = self.sat_position
        turn = OMEGA_EARTH / SPEED_OF_LIGHT * np.stack([-s[:, 1], s[:, 0], np.zeros(len(s))], axis=1)
        return np.sum(s * s, axis=1), turn

    def variances(self) -> np.ndarray:
        return self.std_m**2
