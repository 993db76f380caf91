"""A synthetic GPS + BeiDou constellation on circular Keplerian orbits, for the GNSS simulation.

Orbits are circles (no eccentricity, no perturbations): a satellite's argument of latitude grows at the
mean motion sqrt(GM / a^3) of its radius a. The shapes are the real ones:

* GPS: 24 satellites in 6 planes (right ascensions 60 deg apart) of 4, a = 26 560 km, i = 55 deg; slots 90
  deg apart in a plane, shifted by 15 deg from one plane to the next (a Walker 24/6/1 pattern). PRN 1-24.
* BeiDou MEO: 24 satellites in 3 planes of 8, a = 27 906 km, i = 55 deg (Walker 24/3/1). PRN 19-42.
* BeiDou IGSO: 5 satellites, geosynchronous radius, i = 55 deg, on two figure-of-eight ground tracks
  crossing the equator at 118 E (three satellites) and 95 E (two). PRN 6-10.
* BeiDou GEO: 5 satellites over the equator at the real slots 140, 80, 110.5, 160 and 58.75 E. PRN 1-5.

The geosynchronous radius is the one whose mean motion equals the Earth's rotation rate exactly,
(GM / omega_e^2)^(1/3) = 42 164.2 km, so a GEO satellite stays over its longitude and an IGSO's ground
track closes every sidereal day. ECEF = Rz(-theta(t)) ECI with the Earth rotation angle theta(t) =
omega_e t (zero at t = 0, continuous GPS seconds): the simulation's own epoch, no real sky is implied.

Satellite clocks: offset a0 + a1 (t - t_ref), a0 uniform in +-0.5 ms and a1 ~ N(0, 1e-11) s/s,
drawn once from a fixed seed (the constellation is the same in every run).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edgepos.gnss.orbits import GM, OMEGA_EARTH

GPS_RADIUS_M = 26_560_000.0
BDS_MEO_RADIUS_M = 27_906_000.0
GEOSYNCHRONOUS_RADIUS_M = (GM["C"] / OMEGA_EARTH**2) ** (1.0 / 3.0)
INCLINATION_RAD = math.radians(55.0)
BDS_GEO_LONGITUDES_DEG = {1: 140.0, 2: 80.0, 3: 110.5, 4: 160.0, 5: 58.75}
#: IGSO PRN -> (equator-crossing longitude deg, argument of latitude at t = 0 deg).
BDS_IGSO_TRACKS = {6: (118.0, 0.0), 7: (118.0, 120.0), 8: (118.0, 240.0), 9: (95.0, 60.0), 10: (95.0, 240.0)}
CLOCK_SEED = 20180416


@dataclass(frozen=True)
class Constellation:
    """Circular orbits of ``n`` satellites as parallel arrays; positions and clocks at any GPS time."""

    systems: tuple[str, ...]
    """RINEX system letter per satellite ("G" GPS, "C" BeiDou)."""
    prns: np.ndarray
    kinds: tuple[str, ...]
    """"MEO", "IGSO" or "GEO"."""
    radius: np.ndarray
    """Orbit radius (m)."""
    inclination: np.ndarray
    raan: np.ndarray
    """Right ascension of the ascending node in the inertial frame (rad)."""
    latitude0: np.ndarray
    """Argument of latitude at t = 0 (rad)."""
    mean_motion: np.ndarray
    """rad/s."""
    clock_offset: np.ndarray
    """a0 (s) at ``clock_epoch``."""
    clock_drift: np.ndarray
    """a1 (s/s)."""
    clock_epoch: float = 0.0

    def __len__(self) -> int:
        return len(self.systems)

    @property
    def names(self) -> list[str]:
        """RINEX-style satellite names, e.g. "G07", "C03"."""
        return [f"{system}{int(prn):02d}" for system, prn in zip(self.systems, self.prns)]

    def ecef(self, t: np.ndarray | float) -> np.ndarray:
        """ECEF positions (..., n, 3) of every satellite at the common GPS times ``t`` (...,) (s)."""
        t = np.asarray(t, float)[..., None]
        return self.ecef_each(np.broadcast_to(t, t.shape[:-1] + (len(self),)))

    def ecef_each(self, t: np.ndarray) -> np.ndarray:
        """ECEF positions (..., n, 3) when satellite j has its own GPS time ``t[..., j]`` (transmit
        times), each in the ECEF frame of its own time."""
        t = np.asarray(t, float)
        u = self.latitude0 + self.mean_motion * t
        x_plane, y_plane = self.radius * np.cos(u), self.radius * np.sin(u)
        cos_i, sin_i = np.cos(self.inclination), np.sin(self.inclination)
        cos_o, sin_o = np.cos(self.raan), np.sin(self.raan)
        x = x_plane * cos_o - y_plane * cos_i * sin_o
        y = x_plane * sin_o + y_plane * cos_i * cos_o
        z = y_plane * sin_i
        theta = OMEGA_EARTH * t
        cos_t, sin_t = np.cos(theta), np.sin(theta)
        return np.stack([cos_t * x + sin_t * y, -sin_t * x + cos_t * y, z], axis=-1)

    def ecef_velocity_each(self, t: np.ndarray) -> np.ndarray:
        """Earth-fixed velocities (..., n, 3) (m/s), the time derivatives of :meth:`ecef_each` at the same
        per-satellite GPS times: the orbital motion rotated into the Earth-fixed frame, less the frame's
        rotation (omega_e x r)."""
        t = np.asarray(t, float)
        u = self.latitude0 + self.mean_motion * t
        x_plane, y_plane = self.radius * np.cos(u), self.radius * np.sin(u)
        vx_plane, vy_plane = -self.mean_motion * y_plane, self.mean_motion * x_plane
        cos_i, sin_i = np.cos(self.inclination), np.sin(self.inclination)
        cos_o, sin_o = np.cos(self.raan), np.sin(self.raan)
        x = x_plane * cos_o - y_plane * cos_i * sin_o
        y = x_plane * sin_o + y_plane * cos_i * cos_o
        vx = vx_plane * cos_o - vy_plane * cos_i * sin_o
        vy = vx_plane * sin_o + vy_plane * cos_i * cos_o
        vz = vy_plane * sin_i
        theta = OMEGA_EARTH * t
        cos_t, sin_t = np.cos(theta), np.sin(theta)
        x_fixed, y_fixed = cos_t * x + sin_t * y, -sin_t * x + cos_t * y
        return np.stack(
            [
                cos_t * vx + sin_t * vy + OMEGA_EARTH * y_fixed,
                -sin_t * vx + cos_t * vy - OMEGA_EARTH * x_fixed,
                vz,
            ],
            axis=-1,
        )

    def clock(self, t: np.ndarray) -> np.ndarray:
        """Satellite clock offsets (s) at per-satellite GPS times ``t`` (..., n)."""
        return self.clock_offset + self.clock_drift * (np.asarray(t, float) - self.clock_epoch)


def _walker(total: int, planes: int, phasing: int) -> tuple[np.ndarray, np.ndarray]:
    """Right ascensions and arguments of latitude (rad) of a Walker total/planes/phasing pattern."""
    per_plane = total // planes
    plane = np.repeat(np.arange(planes), per_plane)
    slot = np.tile(np.arange(per_plane), planes)
    raan = 2.0 * math.pi * plane / planes
    latitude = 2.0 * math.pi * slot / per_plane + 2.0 * math.pi * phasing * plane / total
    return raan, latitude


def gps_bds_constellation(clock_epoch: float = 0.0) -> Constellation:
    """The GPS + BeiDou (MEO, IGSO, GEO) constellation described in the module docstring; satellite clock
    offsets are a0 at ``clock_epoch`` (GPS seconds), the reference time of the simulated clock upload."""
    systems: list[str] = []
    prns: list[int] = []
    kinds: list[str] = []
    radius: list[float] = []
    inclination: list[float] = []
    raan: list[float] = []
    latitude: list[float] = []

    def add(system: str, prn: int, kind: str, a: float, inc: float, node: float, u0: float) -> None:
        systems.append(system)
        prns.append(prn)
        kinds.append(kind)
        radius.append(a)
        inclination.append(inc)
        raan.append(node)
        latitude.append(u0)

    gps_raan, gps_u = _walker(24, 6, 1)
    for k in range(24):
        add("G", k + 1, "MEO", GPS_RADIUS_M, INCLINATION_RAD, gps_raan[k], gps_u[k])
    for prn, longitude in BDS_GEO_LONGITUDES_DEG.items():
        # theta(0) = 0, so at t = 0 inertial and Earth-fixed longitudes agree.
        add("C", prn, "GEO", GEOSYNCHRONOUS_RADIUS_M, 0.0, 0.0, math.radians(longitude))
    for prn, (crossing, u0_deg) in BDS_IGSO_TRACKS.items():
        u0 = math.radians(u0_deg)
        # The node passes the crossing longitude when u = 0, i.e. at t = -u0 / omega_e.
        add("C", prn, "IGSO", GEOSYNCHRONOUS_RADIUS_M, INCLINATION_RAD, math.radians(crossing) - u0, u0)
    meo_raan, meo_u = _walker(24, 3, 1)
    for k in range(24):
        add("C", 19 + k, "MEO", BDS_MEO_RADIUS_M, INCLINATION_RAD, meo_raan[k], meo_u[k])

    radius_array = np.array(radius)
    gm = np.array([GM[system] for system in systems])
    rng = np.random.default_rng(CLOCK_SEED)
    count = len(systems)
    return Constellation(
        systems=tuple(systems),
        prns=np.array(prns),
        kinds=tuple(kinds),
        radius=radius_array,
        inclination=np.array(inclination),
        raan=np.array(raan),
        latitude0=np.array(latitude),
        mean_motion=np.sqrt(gm / radius_array**3),
        clock_offset=rng.uniform(-5e-4, 5e-4, count),
        clock_drift=rng.normal(0.0, 1e-11, count),
        clock_epoch=clock_epoch,
    )
