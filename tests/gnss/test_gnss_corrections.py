"""Klobuchar ionosphere and Saastamoinen troposphere."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.gnss.corrections import (
    F_BDS_B1I,
    F_GPS_L1,
    klobuchar_delay,
    klobuchar_l1_delay,
    saastamoinen_delay,
    saastamoinen_zenith,
)

ALPHA = (0.382e-07, 0.149e-07, -0.179e-06, 0.0)
BETA = (0.143e06, 0.0, -0.328e06, 0.113e06)
C = 299792458.0


def test_klobuchar_published_example() -> None:
    """Ovstedal's GPS Toolbox example (NGS GPS Toolbox, Klobuchar programs): receiver 40 N 260 E (i.e. 100 W),
    azimuth 210 deg, elevation 20 deg, GPS time of week 593100 s -> 23.784 m on L1."""
    delay = klobuchar_l1_delay(
        ALPHA,
        BETA,
        math.radians(40.0),
        math.radians(260.0),
        math.radians(20.0),
        math.radians(210.0),
        593100.0,
    )
    assert float(delay) == pytest.approx(23.784, abs=1e-3)


def test_klobuchar_night_floor_and_day_bounds() -> None:
    lat, lon = math.radians(41.6), math.radians(2.35)
    # Local midnight at the pierce point (lon ~ 2.35 E): zenith delay is the 5 ns floor times the obliquity.
    night = float(klobuchar_l1_delay(ALPHA, BETA, lat, lon, math.pi / 2, 0.0, 0.0))
    obliquity_zenith = 1.0 + 16.0 * (0.53 - 0.5) ** 3
    assert night == pytest.approx(C * 5e-9 * obliquity_zenith, rel=1e-12)
    hours = np.arange(0, 86400, 600.0)
    day = np.array([float(klobuchar_l1_delay(ALPHA, BETA, lat, lon, math.pi / 2, 0.0, t)) for t in hours])
    assert day.min() == pytest.approx(night) and day.max() > 3.0 * night
    peak_hour = hours[np.argmax(day)] / 3600.0 + math.degrees(lon) / 15.0
    assert peak_hour == pytest.approx(14.0, abs=0.2)  # the model's maximum is at 14:00 local time
    # Lower elevations see more ionosphere, up to the obliquity factor's bound of about 3.
    el = np.radians([90.0, 45.0, 20.0, 5.0])
    slant = klobuchar_l1_delay(ALPHA, BETA, lat, lon, el, np.zeros(4), 50400.0)
    assert np.all(np.diff(slant) > 0.0) and slant[-1] / slant[0] < 3.1


def test_klobuchar_frequency_scaling_for_beidou() -> None:
    args = (ALPHA, BETA, 0.7, 0.04, np.array([0.5]), np.array([1.0]), 45000.0)
    ratio = klobuchar_delay(*args, frequency_hz=F_BDS_B1I) / klobuchar_l1_delay(*args)
    assert float(ratio[0]) == pytest.approx((F_GPS_L1 / F_BDS_B1I) ** 2)


def test_saastamoinen_sea_level_zenith() -> None:
    hydrostatic, wet = saastamoinen_zenith(math.radians(45.0), 0.0)
    assert hydrostatic == pytest.approx(2.3069, abs=2e-3)  # 0.0022768 * 1013.25 hPa
    assert 0.05 < wet < 0.2
    assert float(saastamoinen_delay(math.radians(45.0), 0.0, math.pi / 2)) == pytest.approx(hydrostatic + wet)
    # Higher is drier and thinner; lower elevation maps the zenith delay up by 1/sin(el).
    assert sum(saastamoinen_zenith(math.radians(45.0), 2000.0)) < 0.85 * (hydrostatic + wet)
    assert float(saastamoinen_delay(0.7, 0.0, math.radians(30.0))) == pytest.approx(
        2.0 * float(saastamoinen_delay(0.7, 0.0, math.pi / 2))
    )
    assert float(saastamoinen_delay(0.7, 4.0e5, 0.5)) == 0.0


def test_saastamoinen_is_finite_and_falls_with_height_up_to_the_cut_off() -> None:
    # A least-squares iteration can pass through any height; 38-100 km used to give inf or a complex
    # pressure (TypeError, a 500 in the service). The delay must stay finite, >= 0 and non-increasing.
    heights = np.concatenate([np.linspace(-999.0, 1.2e5, 4001), [38417.0, 44330.0, 44331.0, 99999.0]])
    heights.sort()
    delays = np.array([float(saastamoinen_delay(0.7, float(h), 0.3)) for h in heights])
    assert np.all(np.isfinite(delays)) and np.all(delays >= 0.0)
    assert np.all(np.diff(delays) <= 1e-12)
    assert float(saastamoinen_delay(0.7, 30_000.0, math.pi / 2)) < 0.02
