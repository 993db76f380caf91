"""Range-rate (Doppler) observation model of the tightly coupled pipeline: the time derivative of the
pseudorange model (``pseudorange.py``), so both describe the same geometry and clocks.

The pseudorange model is rho = |s - r| + omega_e (x_s y_r - y_s x_r) / c + b_sys + known, with s the
satellite at transmit time (ECEF of that instant) and r the receiver at reception. Its rate is

    rho_dot = u . (v_s - v_r) + omega_e (vx_s y_r + x_s vy_r - vy_s x_r - y_s vx_r) / c + d - c dt_s_dot

with u the unit vector from receiver to satellite, v_s the satellite's ECEF velocity, v_r the receiver's
(its east/north/up velocity state rotated to ECEF at its own latitude and longitude), d the receiver clock
drift state (m/s, common to every constellation) and dt_s_dot the satellite clock drift (s/s). A receiver
measures -lambda D = rho_dot for a Doppler D (RINEX sign: positive when the satellite approaches). The
rates of the ionosphere and troposphere delays (millimetres per second) are left out. Vectorised over any
leading axes of the states (particles, sigma points).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from edgepos.core.motion.riss import DRIFT, VE, VN, VU, GeodeticAnchor
from edgepos.core.numerics import FloatArray
from edgepos.gnss.geodesy import geodetic_to_ecef
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT


def enu_velocity_to_ecef(lat: np.ndarray, lon: np.ndarray, v_enu: np.ndarray) -> np.ndarray:
    """ECEF velocity (..., 3) of east/north/up velocities (..., 3) at geodetic latitudes/longitudes (...)."""
    sin_lat, cos_lat, sin_lon, cos_lon = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    ve, vn, vu = v_enu[..., 0], v_enu[..., 1], v_enu[..., 2]
    return np.stack(
        [
            -sin_lon * ve - sin_lat * cos_lon * vn + cos_lat * cos_lon * vu,
            cos_lon * ve - sin_lat * sin_lon * vn + cos_lat * sin_lon * vu,
            cos_lat * vn + sin_lat * vu,
        ],
        axis=-1,
    )


@dataclass(frozen=True)
class RangeRateModel:
    """m range rates: satellite positions and velocities (m, 3) ECEF at transmit time, known additive terms
    (m,) in m/s (-c times the satellite clock drift) and noise standard deviations (m,) in m/s."""

    anchor: GeodeticAnchor
    sat_position: np.ndarray
    sat_velocity: np.ndarray
    known_mps: np.ndarray
    std_mps: np.ndarray

    @classmethod
    def build(
        cls,
        anchor: GeodeticAnchor,
        sat_position: np.ndarray,
        sat_velocity: np.ndarray,
        sat_clock_drift: np.ndarray,
        std_mps: np.ndarray,
    ) -> RangeRateModel:
        """From satellite states and clock drifts (s/s), as the orbits give them."""
        return cls(
            anchor,
            np.asarray(sat_position, float),
            np.asarray(sat_velocity, float),
            -SPEED_OF_LIGHT * np.asarray(sat_clock_drift, float),
            np.asarray(std_mps, float),
        )

    @property
    def dim(self) -> int:
        return len(self.known_mps)

    def predict(self, states: np.ndarray) -> np.ndarray:
        """Predicted range rates (..., m) of states (..., DIM)."""
        lat, lon, height = self.anchor.geodetic(states)
        return self.predict_at(states, lat, lon, geodetic_to_ecef(lat, lon, height))

    def predict_at(
        self, states: np.ndarray, lat: np.ndarray, lon: np.ndarray, receiver: np.ndarray
    ) -> np.ndarray:
        """:meth:`predict` with the states' latitudes, longitudes (...) and ECEF positions (..., 3) already
        computed (shared with the pseudorange model when both are updated together)."""
        velocity = enu_velocity_to_ecef(lat, lon, states[..., [VE, VN, VU]])
        s, vs = self.sat_position, self.sat_velocity
        # orbits.sagnac_range_rate written as products with the satellites' (3, m) columns, so that the
        # particles x sigma points x satellites terms are matrix products, not (..., m, 3) temporaries:
        # |s - r|^2 = |s|^2 - 2 r.s + |r|^2 (the cancellation costs 1e-9 m of range, nothing of the rate).
        square, s_dot_vs, turn_s, turn_r = self._geometry
        r_dot_s = receiver @ s.T
        distance = np.sqrt(
            np.maximum(square - 2.0 * r_dot_s + np.sum(receiver * receiver, axis=-1)[..., None], 0.0)
        )
        along = s_dot_vs - receiver @ vs.T - velocity @ s.T + np.sum(receiver * velocity, axis=-1)[..., None]
        sagnac = receiver @ turn_s.T + velocity @ turn_r.T
        rates: FloatArray = along / distance + sagnac + states[..., DRIFT, None] + self.known_mps
        return rates

    def variances(self) -> np.ndarray:
        return self.std_mps**2

    @functools.cached_property
    def _geometry(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per satellite, computed once per model: |s|^2, s . v_s, and the Sagnac rate's rows (m, 3) that
        multiply the receiver's position and velocity (omega / c included)."""
        s, vs = self.sat_position, self.sat_velocity
        zeros = np.zeros(len(s))
        scale = OMEGA_EARTH / SPEED_OF_LIGHT
        turn_s = scale * np.stack([-vs[:, 1], vs[:, 0], zeros], axis=1)  # omega x-terms of v_s with r
        turn_r = scale * np.stack([-s[:, 1], s[:, 0], zeros], axis=1)  # ... and of s with v_r
        return np.sum(s * s, axis=1), np.sum(s * vs, axis=1), turn_s, turn_r
