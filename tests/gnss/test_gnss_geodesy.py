"""WGS-84 geodesy: geodetic <-> ECEF round trips over the globe, ENU and elevation/azimuth closed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.gnss.geodesy import (
    WGS84_A,
    WGS84_B,
    ecef_to_enu,
    ecef_to_geodetic,
    elevation_azimuth,
    enu_to_ecef,
    geodetic_to_ecef,
)
from hypothesis import given, settings
from hypothesis import strategies as st

latitudes = st.floats(-math.pi / 2, math.pi / 2) | st.sampled_from([-math.pi / 2, 0.0, math.pi / 2])
longitudes = st.floats(-math.pi, math.pi)
heights = st.floats(-5000.0, 4.0e7)


@settings(max_examples=300, deadline=None)
@given(latitudes, longitudes, heights)
def test_geodetic_ecef_round_trip(lat: float, lon: float, height: float) -> None:
    ecef = geodetic_to_ecef(lat, lon, height)
    lat2, lon2, height2 = ecef_to_geodetic(ecef)
    assert np.linalg.norm(geodetic_to_ecef(lat2, lon2, height2) - ecef) < 1e-8 * max(
        1.0, np.linalg.norm(ecef) / 6.4e6
    )
    assert abs(float(height2) - height) < 1e-8 * max(1.0, abs(height) / 6.4e6)
    assert abs(float(lat2) - lat) < 1e-14 * 1e3


def test_closed_cases() -> None:
    assert geodetic_to_ecef(0.0, 0.0, 0.0) == pytest.approx([WGS84_A, 0.0, 0.0])
    assert geodetic_to_ecef(math.pi / 2, 0.0, 100.0) == pytest.approx([0.0, 0.0, WGS84_B + 100.0], abs=1e-9)
    lat, lon, height = ecef_to_geodetic(np.array([0.0, 0.0, -WGS84_B - 50.0]))
    assert (float(lat), float(height)) == pytest.approx((-math.pi / 2, 50.0), abs=1e-9)
    lat, lon, height = ecef_to_geodetic(np.array([0.0, WGS84_A + 10.0, 0.0]))
    assert (float(lat), float(lon), float(height)) == pytest.approx((0.0, math.pi / 2, 10.0), abs=1e-12)


def test_vectorised_shapes() -> None:
    lats, lons = np.linspace(-1.5, 1.5, 7), np.linspace(-3, 3, 7)
    ecef = geodetic_to_ecef(lats, lons, np.full(7, 200.0))
    assert ecef.shape == (7, 3)
    back = ecef_to_geodetic(ecef)
    assert np.allclose(back[0], lats, atol=1e-14) and np.allclose(back[2], 200.0, atol=1e-8)


def test_enu_and_elevation_azimuth() -> None:
    origin = geodetic_to_ecef(math.radians(41.64), math.radians(2.35), 250.0)
    enu = np.array([[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 100.0], [30.0, -40.0, 5.0]])
    ecef = enu_to_ecef(enu, origin)
    assert np.allclose(ecef_to_enu(ecef, origin), enu, atol=1e-9)
    # A point straight up along the ellipsoid normal is at 90 deg elevation; the height grows by 100 m.
    assert float(ecef_to_geodetic(ecef[2])[2]) == pytest.approx(350.0, abs=1e-6)
    el, az = elevation_azimuth(origin, ecef)
    assert np.degrees(el[:3]) == pytest.approx([0.0, 0.0, 90.0], abs=1e-9)
    assert np.degrees(az[:2]) == pytest.approx([90.0, 0.0], abs=1e-9)
    assert float(el[3]) == pytest.approx(math.atan2(5.0, 50.0))
    assert float(az[3]) == pytest.approx(math.atan2(30.0, -40.0))
    # Due south and due west wrap into [0, 2 pi).
    el, az = elevation_azimuth(
        origin, enu_to_ecef(np.array([[0.0, -10.0, -10.0], [-10.0, 0.0, 0.0]]), origin)
    )
    assert np.degrees(az) == pytest.approx([180.0, 270.0]) and np.degrees(el) == pytest.approx(
        [-45.0, 0.0], abs=1e-7
    )
