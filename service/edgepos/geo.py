"""WGS-84 conversions between a site's local east-north-up plane and geodetic coordinates.

The service works in a site-local frame (x east, y north, metres). When the operator gives the
site's origin as latitude, longitude and ellipsoidal height, a point (e, n, u) of the local tangent
plane at that origin maps to the globe exactly: ENU -> ECEF (a rotation plus the origin's ECEF
position) -> geodetic (Heikkinen's closed form, sub-millimetre for points near the surface).
Angles are radians; lengths metres. Pure ``math``: no web or numpy imports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

WGS84_A = 6378137.0
"""Semi-major axis (m)."""
WGS84_F = 1.0 / 298.257223563
"""Flattening."""
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""
WGS84_EP2 = (WGS84_A**2 - WGS84_B**2) / WGS84_B**2
"""Second eccentricity squared."""


def geodetic_to_ecef(lat: float, lon: float, height: float) -> tuple[float, float, float]:
    """Latitude, longitude (rad) and ellipsoidal height (m) -> Earth-centred Earth-fixed (m)."""
    sin_lat = math.sin(lat)
    prime_vertical = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    horizontal = (prime_vertical + height) * math.cos(lat)
    return (
        horizontal * math.cos(lon),
        horizontal * math.sin(lon),
        (prime_vertical * (1.0 - WGS84_E2) + height) * sin_lat,
    )


def ecef_to_geodetic(x: float, y: float, z: float) -> tuple[float, float, float]:
    """Earth-centred Earth-fixed (m) -> latitude, longitude (rad), ellipsoidal height (m).

    Heikkinen (1982) closed form, as given by Zhu (1993), valid away from the Earth's centre."""
    a, b, e2 = WGS84_A, WGS84_B, WGS84_E2
    p = math.hypot(x, y)
    f_term = 54.0 * b * b * z * z
    g_term = p * p + (1.0 - e2) * z * z - e2 * (a * a - b * b)
    c_term = e2 * e2 * f_term * p * p / g_term**3
    s_term = math.cbrt(1.0 + c_term + math.sqrt(c_term * c_term + 2.0 * c_term))
    k_term = s_term + 1.0 + 1.0 / s_term
    p_term = f_term / (3.0 * k_term * k_term * g_term * g_term)
    q_term = math.sqrt(1.0 + 2.0 * e2 * e2 * p_term)
    r0 = -(p_term * e2 * p) / (1.0 + q_term) + math.sqrt(
        max(
            0.0,
            0.5 * a * a * (1.0 + 1.0 / q_term)
            - p_term * (1.0 - e2) * z * z / (q_term * (1.0 + q_term))
            - 0.5 * p_term * p * p,
        )
    )
    u_term = math.hypot(p - e2 * r0, z)
    v_term = math.sqrt((p - e2 * r0) ** 2 + (1.0 - e2) * z * z)
    z0 = b * b * z / (a * v_term)
    height = u_term * (1.0 - b * b / (a * v_term))
    lat = math.atan2(z + WGS84_EP2 * z0, p)
    lon = math.atan2(y, x)
    return lat, lon, height


@dataclass(frozen=True)
class GeodeticOrigin:
    """The site frame's origin: latitude, longitude (rad) and ellipsoidal height (m)."""

    lat: float
    lon: float
    height: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lat) and abs(self.lat) <= math.pi / 2):
            raise ValueError("origin latitude must be within [-pi/2, pi/2] rad")
        if not (math.isfinite(self.lon) and abs(self.lon) <= math.pi):
            raise ValueError("origin longitude must be within [-pi, pi] rad")
        if not math.isfinite(self.height):
            raise ValueError("origin height must be finite")

    @classmethod
    def from_degrees(cls, lat_deg: float, lon_deg: float, height: float = 0.0) -> GeodeticOrigin:
        return cls(math.radians(lat_deg), math.radians(lon_deg), height)

    def enu_to_ecef(self, east: float, north: float, up: float = 0.0) -> tuple[float, float, float]:
        """A point of the local east-north-up frame (m) in ECEF (m)."""
        x0, y0, z0 = geodetic_to_ecef(self.lat, self.lon, self.height)
        sin_lat, cos_lat = math.sin(self.lat), math.cos(self.lat)
        sin_lon, cos_lon = math.sin(self.lon), math.cos(self.lon)
        return (
            x0 - sin_lon * east - sin_lat * cos_lon * north + cos_lat * cos_lon * up,
            y0 + cos_lon * east - sin_lat * sin_lon * north + cos_lat * sin_lon * up,
            z0 + cos_lat * north + sin_lat * up,
        )

    def enu_to_geodetic(self, east: float, north: float, up: float = 0.0) -> tuple[float, float, float]:
        """A point of the local east-north-up frame (m) -> latitude, longitude (rad), height (m)."""
        return ecef_to_geodetic(*self.enu_to_ecef(east, north, up))

    def geodetic_to_enu(
        self, lat: float, lon: float, height: float | None = None
    ) -> tuple[float, float, float]:
        """Latitude, longitude (rad) and ellipsoidal height (m; the origin's when None) -> a point of the
        local east-north-up frame (m): the inverse of :meth:`enu_to_geodetic`."""
        x, y, z = geodetic_to_ecef(lat, lon, self.height if height is None else height)
        x0, y0, z0 = geodetic_to_ecef(self.lat, self.lon, self.height)
        dx, dy, dz = x - x0, y - y0, z - z0
        sin_lat, cos_lat = math.sin(self.lat), math.cos(self.lat)
        sin_lon, cos_lon = math.sin(self.lon), math.cos(self.lon)
        return (
            -sin_lon * dx + cos_lon * dy,
            -sin_lat * cos_lon * dx - sin_lat * sin_lon * dy + cos_lat * dz,
            cos_lat * cos_lon * dx + cos_lat * sin_lon * dy + sin_lat * dz,
        )
