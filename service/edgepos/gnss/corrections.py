"""Broadcast ionosphere (Klobuchar) and Saastamoinen troposphere delays, vectorised over satellites.

Klobuchar follows IS-GPS-200 20.3.3.5.2.5 (angles in semicircles inside the model, the 8 header
coefficients alpha/beta); the L1 delay is scaled by (f_L1 / f)^2 for other frequencies (BeiDou B1I,
Galileo E1 = L1). Saastamoinen's zenith delays use a standard atmosphere (pressure and temperature from the
height, fixed relative humidity) and the 1/cos(z) mapping, as in common single-point practice.
All outputs are delays in metres to add to the geometric range.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from edgepos.gnss.orbits import SPEED_OF_LIGHT

F_GPS_L1 = 1575.42e6
F_BDS_B1I = 1561.098e6
F_GAL_E1 = 1575.42e6
CARRIER_HZ: dict[tuple[str, str], float] = {
    ("G", "1"): F_GPS_L1,
    ("G", "2"): 1227.60e6,
    ("G", "5"): 1176.45e6,
    ("J", "1"): F_GPS_L1,
    ("C", "2"): F_BDS_B1I,
    ("C", "1"): 1575.42e6,
    ("C", "7"): 1207.14e6,
    ("C", "6"): 1268.52e6,
    ("E", "1"): F_GAL_E1,
    ("E", "5"): 1176.45e6,
    ("E", "7"): 1207.14e6,
}
"""(system, RINEX band digit) -> carrier frequency (Hz)."""


def carrier_frequency(system: str, code: str) -> float:
    """Carrier frequency (Hz) of a RINEX observation code such as ``C1C``; KeyError if unknown."""
    try:
        return CARRIER_HZ[(system, code[1])]
    except KeyError:
        raise KeyError(f"unknown carrier for system {system} code {code}") from None


def klobuchar_l1_delay(
    alpha: Sequence[float],
    beta: Sequence[float],
    lat: float,
    lon: float,
    elevation: np.ndarray | float,
    azimuth: np.ndarray | float,
    gps_seconds: float,
) -> np.ndarray:
    """GPS L1 ionospheric group delay (m) of the Klobuchar model.

    ``lat``/``lon`` of the receiver (rad), ``elevation``/``azimuth`` (rad) per satellite, ``gps_seconds``
    any GPS time (only the time of day matters). Night-time floor 5 ns times the obliquity factor.
    """
    el = np.asarray(elevation, float) / np.pi
    az = np.asarray(azimuth, float)
    psi = 0.0137 / (el + 0.11) - 0.022
    phi_i = np.clip(lat / np.pi + psi * np.cos(az), -0.416, 0.416)
    lam_i = lon / np.pi + psi * np.sin(az) / np.cos(phi_i * np.pi)
    phi_m = phi_i + 0.064 * np.cos((lam_i - 1.617) * np.pi)
    local_time = np.mod(4.32e4 * lam_i + gps_seconds, 86400.0)
    amplitude = np.maximum(np.polyval(list(alpha)[::-1], phi_m), 0.0)
    period = np.maximum(np.polyval(list(beta)[::-1], phi_m), 72000.0)
    x = 2.0 * np.pi * (local_time - 50400.0) / period
    obliquity = 1.0 + 16.0 * (0.53 - el) ** 3
    day = np.abs(x) < 1.57
    cosine = 1.0 - x * x / 2.0 + x**4 / 24.0
    seconds = obliquity * (5e-9 + np.where(day, amplitude * cosine, 0.0))
    return SPEED_OF_LIGHT * seconds


def klobuchar_delay(
    alpha: Sequence[float],
    beta: Sequence[float],
    lat: float,
    lon: float,
    elevation: np.ndarray,
    azimuth: np.ndarray,
    gps_seconds: float,
    frequency_hz: np.ndarray | float,
) -> np.ndarray:
    """Klobuchar delay (m) scaled from L1 to each signal's carrier by (f_L1 / f)^2."""
    l1 = klobuchar_l1_delay(alpha, beta, lat, lon, elevation, azimuth, gps_seconds)
    return l1 * (F_GPS_L1 / np.asarray(frequency_hz, float)) ** 2


ATMOSPHERE_TOP_M = 30_000.0
"""Heights above this use the standard atmosphere at this height. The model's formulas stop making sense
higher up (the pressure base 1 - 2.2557e-5 h turns negative at 44.3 km, the temperature falls towards zero
and the vapour formula divides by zero near 38 km), while the delay left there is a few millimetres. A
least-squares iteration may pass through such heights on its way to the ground."""


def standard_atmosphere(height_m: float, relative_humidity: float = 0.7) -> tuple[float, float, float]:
    """Pressure (hPa), temperature (K) and water-vapour partial pressure (hPa) at an ellipsoidal height
    (clamped to [0, ATMOSPHERE_TOP_M])."""
    h = min(max(height_m, 0.0), ATMOSPHERE_TOP_M)
    pressure = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    temperature = 15.0 - 6.5e-3 * h + 273.16
    vapour = 6.108 * relative_humidity * np.exp((17.15 * temperature - 4684.0) / (temperature - 38.45))
    return pressure, temperature, float(vapour)


def saastamoinen_zenith(lat: float, height_m: float, relative_humidity: float = 0.7) -> tuple[float, float]:
    """(hydrostatic, wet) zenith delays (m) of Saastamoinen's model in the standard atmosphere."""
    pressure, temperature, vapour = standard_atmosphere(height_m, relative_humidity)
    h = min(max(height_m, 0.0), ATMOSPHERE_TOP_M)
    hydrostatic = 0.0022768 * pressure / (1.0 - 0.00266 * np.cos(2.0 * lat) - 0.00028 * h / 1e3)
    wet = 0.002277 * (1255.0 / temperature + 0.05) * vapour
    return float(hydrostatic), float(wet)


def saastamoinen_delay(
    lat: float, height_m: float, elevation: np.ndarray | float, relative_humidity: float = 0.7
) -> np.ndarray:
    """Slant tropospheric delay (m): zenith delay over sin(elevation); zero for receivers far above the
    troposphere (> 100 km) and floored at 5 degrees of elevation to keep the mapping finite."""
    el = np.maximum(np.asarray(elevation, float), np.deg2rad(5.0))
    if not -1000.0 < height_m < 1e5:
        return np.zeros_like(el)
    hydrostatic, wet = saastamoinen_zenith(lat, height_m, relative_humidity)
    result: np.ndarray = (hydrostatic + wet) / np.sin(el)
    return result
