"""State layout and motion models of the tightly coupled GNSS pipeline (Jiang & Chen 2018, eq. 4).

State (13): position as curvilinear offsets from a geodetic anchor - ``north`` = (lat - lat0) (R_M0 + h0),
``east`` = (lon - lon0) (R_N0 + h0) cos(lat0), ``up`` = h - h0 (m; a fixed linear rescaling of the paper's
latitude, longitude and height that keeps covariances well conditioned) - then east, north and up velocity
(m/s), pitch, roll, azimuth (rad; azimuth clockwise from north, pitch nose up, roll positive when the left
side rises), a receiver clock bias per constellation (GPS, BeiDou, Galileo; metres, i.e. c times seconds)
and one clock drift (m/s) common to all, then the yaw gyro's bias (rad/s, same sign as its output): the
gyro bias left after start-up calibration turns the dead-reckoned azimuth steadily, tens of times faster
than the gyro's white noise over a minute, so it is estimated rather than covered by process noise; and
the wheel speed's scale error (dimensionless, measured = true x (1 + error)), which tyre wear and pressure
set to about a percent and which pulls the dead reckoning along the track by as much.

Models propagate batches of states (any leading axes) and report which components are stochastic
(``active``): the filters sample and weigh only those; the others follow deterministically.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from edgepos.gnss.geodesy import WGS84_A, WGS84_E2, geodetic_to_ecef

NAMES = (
    "north",
    "east",
    "up",
    "v_east",
    "v_north",
    "v_up",
    "pitch",
    "roll",
    "azimuth",
    "clock_gps",
    "clock_bds",
    "clock_gal",
    "clock_drift",
    "gyro_bias",
    "wheel_scale",
)
DIM = len(NAMES)
NORTH, EAST, UP, VE, VN, VU, PITCH, ROLL, AZIMUTH = range(9)
CLOCK = {"G": 9, "C": 10, "E": 11}
"""State index of each constellation's receiver clock bias (RINEX system letters)."""
DRIFT = 12
GYRO_BIAS = 13
WHEEL_SCALE = 14
ANGLES = np.zeros(DIM, dtype=bool)
ANGLES[[PITCH, ROLL, AZIMUTH]] = True
GRAVITY = 9.80665
OMEGA_EARTH = 7.2921151467e-5


def meridian_radius(lat: np.ndarray | float) -> np.ndarray:
    """R_M: the ellipsoid's meridian radius of curvature (m)."""
    s = np.sin(lat)
    return WGS84_A * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s * s) ** 1.5


def normal_radius(lat: np.ndarray | float) -> np.ndarray:
    """R_N: the prime-vertical radius of curvature (m)."""
    s = np.sin(lat)
    return WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)


@dataclass(frozen=True)
class GeodeticAnchor:
    """The geodetic point (rad, rad, m) the position components are offsets from."""

    lat: float
    lon: float
    height: float

    @property
    def scale_north(self) -> float:
        return float(meridian_radius(self.lat)) + self.height

    @property
    def scale_east(self) -> float:
        return (float(normal_radius(self.lat)) + self.height) * math.cos(self.lat)

    def geodetic(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(latitude, longitude, height) of states (..., DIM)."""
        return (
            self.lat + states[..., NORTH] / self.scale_north,
            self.lon + states[..., EAST] / self.scale_east,
            self.height + states[..., UP],
        )

    def ecef(self, states: np.ndarray) -> np.ndarray:
        """ECEF positions (..., 3) of states (..., DIM)."""
        return geodetic_to_ecef(*self.geodetic(states))

    def offsets(self, lat: float, lon: float, height: float) -> tuple[float, float, float]:
        """The (north, east, up) state components of a geodetic point."""
        return ((lat - self.lat) * self.scale_north, (lon - self.lon) * self.scale_east, height - self.height)


def _clocks(states: np.ndarray, out: np.ndarray, dt: float) -> None:
    for index in CLOCK.values():
        out[..., index] = states[..., index] + states[..., DRIFT] * dt
    out[..., DRIFT] = states[..., DRIFT]


def _clock_noise(q: np.ndarray, dt: float, bias_psd: float, drift_psd: float) -> None:
    """Integrated random walk of bias and drift: the usual two-state clock model, per constellation.

    Every constellation's bias integrates the one drift state, so the drift's share of their noise
    (drift_psd dt^3 / 3) is common to all of them; only the bias random walk is their own. Without
    those cross terms the noise is indefinite as soon as bias_psd < 5/12 drift_psd dt^2 (three
    biases tied to one drift), and the particle filters could not draw from it."""
    clocks = list(CLOCK.values())
    q[np.ix_(clocks, clocks)] = drift_psd * dt**3 / 3.0
    for index in clocks:
        q[index, index] = bias_psd * dt + drift_psd * dt**3 / 3.0
        q[index, DRIFT] = q[DRIFT, index] = drift_psd * dt**2 / 2.0
    q[DRIFT, DRIFT] = drift_psd * dt


def _move(anchor: GeodeticAnchor, states: np.ndarray, out: np.ndarray, dt: float) -> None:
    """Eq. 4's position rows: integrate the new velocity into latitude, longitude and height."""
    lat_prev = anchor.lat + states[..., NORTH] / anchor.scale_north
    out[..., UP] = states[..., UP] + out[..., VU] * dt
    height = anchor.height + out[..., UP]
    out[..., NORTH] = states[..., NORTH] + out[..., VN] * dt * anchor.scale_north / (
        meridian_radius(lat_prev) + height
    )
    lat = anchor.lat + out[..., NORTH] / anchor.scale_north
    out[..., EAST] = states[..., EAST] + out[..., VE] * dt * anchor.scale_east / (
        (normal_radius(lat) + height) * np.cos(lat)
    )


@dataclass(frozen=True)
class RissInput:
    """The paper's system input U (eq. 2): wheel speed v (m/s), its derivative a (m/s^2), forward and
    lateral specific force (m/s^2; x forward, y left) and yaw rate (rad/s, counter-clockwise positive)."""

    wheel_speed: float
    wheel_accel: float
    accel_x: float
    accel_y: float
    gyro_z: float


@dataclass(frozen=True)
class RissModel:
    """Eq. 4: velocity and attitude from the wheel speed, accelerometers and gyro; position integrated.

    Noise (1-sigma) on the inputs, mapped to an additive process noise: wheel speed (m/s), specific
    force (m/s^2), gyro (rad/s); clock bias and drift random-walk densities (m^2/s, m^2/s^3)."""

    anchor: GeodeticAnchor
    u: RissInput
    speed_std: float = 0.1
    accel_std: float = 0.05
    gyro_std: float = 0.005
    clock_bias_psd: float = 1.0
    clock_drift_psd: float = 0.1
    gyro_bias_psd: float = 1e-10

    active = np.ones(DIM, dtype=bool)

    def propagate(self, states: np.ndarray, dt: float) -> np.ndarray:
        u, anchor = self.u, self.anchor
        out = np.empty_like(states)
        pitch = math.asin(max(-1.0, min(1.0, (u.accel_x - u.wheel_accel) / GRAVITY)))
        out[..., PITCH] = pitch
        lateral = (u.accel_y - u.wheel_speed * u.gyro_z) / (GRAVITY * math.cos(pitch))
        out[..., ROLL] = math.asin(max(-1.0, min(1.0, lateral)))
        lat_prev = anchor.lat + states[..., NORTH] / anchor.scale_north
        height_prev = anchor.height + states[..., UP]
        azimuth = (
            states[..., AZIMUTH]
            - (u.gyro_z - states[..., GYRO_BIAS]) * dt
            + OMEGA_EARTH * np.sin(lat_prev) * dt
            + states[..., VE] * np.tan(lat_prev) / (normal_radius(lat_prev) + height_prev) * dt
        )
        out[..., AZIMUTH] = (azimuth + math.pi) % (2.0 * math.pi) - math.pi
        cos_pitch = math.cos(pitch)
        speed = u.wheel_speed / (1.0 + states[..., WHEEL_SCALE])
        out[..., VE] = speed * np.sin(out[..., AZIMUTH]) * cos_pitch
        out[..., VN] = speed * np.cos(out[..., AZIMUTH]) * cos_pitch
        out[..., VU] = speed * math.sin(pitch)
        _move(anchor, states, out, dt)
        _clocks(states, out, dt)
        out[..., GYRO_BIAS] = states[..., GYRO_BIAS]
        out[..., WHEEL_SCALE] = states[..., WHEEL_SCALE]
        return out

    def process_noise(self, dt: float) -> np.ndarray:
        q = np.zeros((DIM, DIM))
        speed_var = self.speed_std**2 + (abs(self.u.wheel_speed) * self.gyro_std * max(dt, 1e-3)) ** 2
        for index in (VE, VN, VU):
            q[index, index] = speed_var
        for index in (NORTH, EAST, UP):
            q[index, index] = speed_var * dt * dt + 1e-6
        q[PITCH, PITCH] = q[ROLL, ROLL] = (self.accel_std / GRAVITY) ** 2 + 1e-8
        q[AZIMUTH, AZIMUTH] = (self.gyro_std * dt) ** 2 + 1e-10
        q[GYRO_BIAS, GYRO_BIAS] = self.gyro_bias_psd * dt + 1e-14
        q[WHEEL_SCALE, WHEEL_SCALE] = 1e-10 * dt + 1e-14  # a tyre's radius changes over hours, not seconds
        _clock_noise(q, dt, self.clock_bias_psd, self.clock_drift_psd)
        return q

    def complete(self, states: np.ndarray) -> np.ndarray:
        return states


@dataclass(frozen=True)
class GnssOnlyModel:
    """Constant velocity with white-noise acceleration (horizontal and vertical 1-sigma densities,
    m/s^2) when no RISS input arrives; attitude follows the velocity (azimuth and pitch of the motion,
    roll held) and is not part of the stochastic state; nor are the gyro bias and wheel scale (held)."""

    anchor: GeodeticAnchor
    accel_std: float = 3.0
    vertical_accel_std: float = 0.3
    clock_bias_psd: float = 1.0
    clock_drift_psd: float = 0.1

    active = np.array([not a for a in ANGLES])
    active[GYRO_BIAS] = active[WHEEL_SCALE] = False

    def propagate(self, states: np.ndarray, dt: float) -> np.ndarray:
        out = np.empty_like(states)
        out[..., VE : VU + 1] = states[..., VE : VU + 1]
        _move(self.anchor, states, out, dt)
        _clocks(states, out, dt)
        out[..., PITCH : AZIMUTH + 1] = states[..., PITCH : AZIMUTH + 1]
        out[..., GYRO_BIAS] = states[..., GYRO_BIAS]
        out[..., WHEEL_SCALE] = states[..., WHEEL_SCALE]
        return self.complete(out)

    def process_noise(self, dt: float) -> np.ndarray:
        """Q over ``dt``: the same few matrices every epoch (dt is the receiver's interval), built once each."""
        q: np.ndarray = _gnss_only_noise(
            self.accel_std, self.vertical_accel_std, self.clock_bias_psd, self.clock_drift_psd, dt
        ).copy()
        return q

    @staticmethod
    def complete(states: np.ndarray) -> np.ndarray:
        """Derive azimuth and pitch from the velocity where the vehicle moves (> 0.5 m/s)."""
        horizontal = np.hypot(states[..., VE], states[..., VN])
        moving = horizontal > 0.5
        states[..., AZIMUTH] = np.where(
            moving, np.arctan2(states[..., VE], states[..., VN]), states[..., AZIMUTH]
        )
        states[..., PITCH] = np.where(moving, np.arctan2(states[..., VU], horizontal), states[..., PITCH])
        return states


@functools.lru_cache(maxsize=64)
def _gnss_only_noise(
    accel_std: float, vertical_accel_std: float, clock_bias_psd: float, clock_drift_psd: float, dt: float
) -> np.ndarray:
    """``GnssOnlyModel.process_noise``'s matrix (read-only): white-noise acceleration per axis, the clocks'
    integrated random walk, and a floor on the held components."""
    q = np.zeros((DIM, DIM))
    for pos, vel, std in (
        (NORTH, VN, accel_std),
        (EAST, VE, accel_std),
        (UP, VU, vertical_accel_std),
    ):
        psd = std * std
        q[pos, pos] = psd * dt**3 / 3.0 + 1e-6
        q[pos, vel] = q[vel, pos] = psd * dt**2 / 2.0
        q[vel, vel] = psd * dt + 1e-8
    _clock_noise(q, dt, clock_bias_psd, clock_drift_psd)
    for index in (PITCH, ROLL, AZIMUTH):
        q[index, index] = 1e-8
    q[GYRO_BIAS, GYRO_BIAS] = q[WHEEL_SCALE, WHEEL_SCALE] = 1e-14
    q.flags.writeable = False
    return q
