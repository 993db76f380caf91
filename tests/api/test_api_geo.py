"""WGS-84 conversions of the optional site origin."""

from __future__ import annotations

import math

import pytest
from edgepos.geo import WGS84_A, WGS84_E2, GeodeticOrigin, ecef_to_geodetic, geodetic_to_ecef


@pytest.mark.parametrize("lat_deg", [-89.9, -60.0, -12.5, 0.0, 0.001, 35.0, 48.1375, 78.0, 89.99])
@pytest.mark.parametrize("height", [-100.0, 0.0, 520.0, 9000.0])
def test_ecef_round_trip(lat_deg, height):
    lat, lon = math.radians(lat_deg), math.radians(11.575 - lat_deg)
    back_lat, back_lon, back_height = ecef_to_geodetic(*geodetic_to_ecef(lat, lon, height))
    assert back_lat == pytest.approx(lat, abs=1e-12)
    assert back_lon == pytest.approx(lon, abs=1e-12)
    assert back_height == pytest.approx(height, abs=1e-6)


def test_known_ecef_values():
    assert geodetic_to_ecef(0.0, 0.0, 0.0) == (WGS84_A, 0.0, 0.0)
    x, y, z = geodetic_to_ecef(math.pi / 2, 0.0, 0.0)
    assert x == pytest.approx(0.0, abs=1e-9) and y == 0.0
    assert z == pytest.approx(6356752.314245, abs=1e-6)  # the WGS-84 semi-minor axis


def test_origin_maps_to_itself():
    origin = GeodeticOrigin.from_degrees(48.1375, 11.575, 520.0)
    lat, lon, height = origin.enu_to_geodetic(0.0, 0.0, 0.0)
    assert lat == pytest.approx(origin.lat, abs=1e-13)
    assert lon == pytest.approx(origin.lon, abs=1e-13)
    assert height == pytest.approx(520.0, abs=1e-6)


def test_east_at_the_equator_is_exact_geometry():
    origin = GeodeticOrigin(0.0, 0.0, 0.0)
    lat, lon, height = origin.enu_to_geodetic(1000.0, 0.0, 0.0)
    assert lat == pytest.approx(0.0, abs=1e-15)
    assert lon == pytest.approx(math.atan2(1000.0, WGS84_A), abs=1e-15)
    assert height == pytest.approx(math.hypot(WGS84_A, 1000.0) - WGS84_A, abs=1e-6)


def test_small_offsets_follow_the_ellipsoid_radii():
    lat0 = math.radians(48.0)
    origin = GeodeticOrigin(lat0, math.radians(11.0), 0.0)
    s = math.sin(lat0)
    meridian = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s * s) ** 1.5
    normal = WGS84_A / math.sqrt(1 - WGS84_E2 * s * s)
    lat, _, _ = origin.enu_to_geodetic(0.0, 10.0)
    _, lon, _ = origin.enu_to_geodetic(10.0, 0.0)
    assert (lat - lat0) * meridian == pytest.approx(10.0, rel=1e-6)
    assert (lon - origin.lon) * normal * math.cos(lat0) == pytest.approx(10.0, rel=1e-6)


def test_origin_is_validated():
    with pytest.raises(ValueError):
        GeodeticOrigin(2.0, 0.0)
    with pytest.raises(ValueError):
        GeodeticOrigin(0.0, float("nan"))


@pytest.mark.parametrize("lat_deg", [-70.0, 0.0, 48.1375, 89.0])
@pytest.mark.parametrize(
    ("east", "north", "up"), [(0.0, 0.0, 0.0), (1234.5, -876.25, 3.0), (-20_000.0, 50_000.0, -40.0)]
)
def test_enu_from_geodetic_inverts_geodetic_from_enu(lat_deg, east, north, up):
    origin = GeodeticOrigin.from_degrees(lat_deg, 11.575, 520.0)
    back = origin.geodetic_to_enu(*origin.enu_to_geodetic(east, north, up))
    assert back == pytest.approx((east, north, up), abs=1e-6)


def test_enu_from_geodetic_defaults_to_the_origins_height():
    origin = GeodeticOrigin.from_degrees(48.1375, 11.575, 520.0)
    assert origin.geodetic_to_enu(origin.lat, origin.lon) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    east, north, up = origin.geodetic_to_enu(origin.lat + 1e-5, origin.lon)  # ~64 m north, on the ellipsoid
    assert east == pytest.approx(0.0, abs=1e-9) and north == pytest.approx(63.7, abs=0.1) and up < 0
