"""WGS-84 geodesy, vectorised: geodetic <-> ECEF, ECEF <-> local east-north-up, elevation and azimuth.

Latitude/longitude in radians, heights and coordinates in metres. Arrays broadcast over leading axes; the
last axis of a position is (x, y, z).
"""

from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0
"""Semi-major axis (m)."""
WGS84_F = 1.0 / 298.257223563
"""Flattening."""
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""
WGS84_B = WGS84_A * (1.0 - WGS84_F)
"""Semi-minor axis (m)."""


def geodetic_to_ecef(
    lat: np.ndarray | float, lon: np.ndarray | float, height: np.ndarray | float
) -> np.ndarray:
    """Geodetic latitude, longitude (rad) and ellipsoidal height (m) -> ECEF (..., 3) in metres."""
    lat, lon, height = np.asarray(lat, float), np.asarray(lon, float), np.asarray(height, float)
    sin_lat = np.sin(lat)
    prime_vertical = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    horizontal = (prime_vertical + height) * np.cos(lat)
    return np.stack(
        [
            horizontal * np.cos(lon),
            horizontal * np.sin(lon),
            (prime_vertical * (1.0 - WGS84_E2) + height) * sin_lat,
        ],
        axis=-1,
    )


def ecef_to_geodetic(position: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (..., 3) -> (latitude, longitude, height), radians and metres.

    Bowring's parametric-latitude start followed by Newton-like fixed-point steps on the reduced latitude
    (converges to machine precision in two or three steps anywhere outside the Earth's deep interior,
    including the poles and the equator). Height uses the form that stays exact at both.
    """
    position = np.asarray(position, dtype=float)
    x, y, z = position[..., 0], position[..., 1], position[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    ep2 = WGS84_E2 / (1.0 - WGS84_E2)
    # Bowring (1976) start: reduced latitude beta from tan(beta) = a z / (b p).
    beta = np.arctan2(WGS84_A * z, WGS84_B * p)
    lat = np.arctan2(z + ep2 * WGS84_B * np.sin(beta) ** 3, p - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    for _ in range(4):
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
        lat = np.arctan2(z + ep2 * WGS84_B * np.sin(beta) ** 3, p - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    sin_lat, cos_lat = np.sin(lat), np.cos(lat)
    prime_vertical = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    height = p * cos_lat + z * sin_lat - WGS84_A * WGS84_A / prime_vertical
    return lat, lon, height


def enu_rotation(lat: float, lon: float) -> np.ndarray:
    """3x3 matrix whose rows are the east, north and up unit vectors (ECEF) at a geodetic point."""
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def ecef_to_enu(position: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """ECEF points (..., 3) -> east, north, up (m) relative to the ECEF ``origin`` (3,)."""
    lat, lon, _ = ecef_to_geodetic(origin)
    result: np.ndarray = (np.asarray(position, float) - origin) @ enu_rotation(float(lat), float(lon)).T
    return result


def enu_to_ecef(enu: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """East, north, up (..., 3) relative to the ECEF ``origin`` -> ECEF points (m)."""
    lat, lon, _ = ecef_to_geodetic(origin)
    result: np.ndarray = np.asarray(enu, float) @ enu_rotation(float(lat), float(lon)) + origin
    return result


def elevation_azimuth(receiver: np.ndarray, satellite: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elevation (rad, -pi/2..pi/2) and azimuth (rad, 0..2 pi clockwise from north) of satellites (n, 3)
    seen from an ECEF receiver position (3,)."""
    lat, lon, _ = ecef_to_geodetic(receiver)
    enu = (np.asarray(satellite, float) - receiver) @ enu_rotation(float(lat), float(lon)).T
    horizontal = np.hypot(enu[..., 0], enu[..., 1])
    elevation = np.arctan2(enu[..., 2], horizontal)
    azimuth = np.mod(np.arctan2(enu[..., 0], enu[..., 1]), 2.0 * np.pi)
    return elevation, azimuth
