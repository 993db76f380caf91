"""gnss_tight's per-epoch satellite geometry in two compiled loops (numba): every satellite's broadcast orbit,
clock, velocity and clock drift at its transmit time, and every satellite's elevation, azimuth, Klobuchar
ionosphere and Saastamoinen troposphere seen from one receiver position.

The same equations as ``gnss.orbits.BroadcastOrbits.transmit_states`` and ``gnss.measurements.Atmosphere.
delays`` (those stay the reference the kernels are tested against, and run when ``EDGEPOS_NUMBA=0``): the
numpy forms cost some hundred and fifty array operations per epoch on twenty satellites, each a few
microseconds of overhead; the loops compute each satellite's values once, with no temporaries. The Kepler
equation iterates every satellite until the slowest converges, as the numpy form's vector iteration does.
The transcendental functions are the C library's, where numpy's are its own SIMD ones: the results agree to
a few units in the last place (tested), not bit for bit.
"""

from __future__ import annotations

import math
import time

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.kernels_base import _jit
from edgepos.core.numerics import FloatArray
from edgepos.gnss.corrections import ATMOSPHERE_TOP_M, F_GPS_L1
from edgepos.gnss.geodesy import WGS84_A, WGS84_B, WGS84_E2, WGS84_F
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet
from edgepos.gnss.orbits import SPEED_OF_LIGHT, VELOCITY_STEP_S, BroadcastOrbits, SatelliteStates

_GEO_COS = math.cos(math.radians(-5.0))
_GEO_SIN = math.sin(math.radians(-5.0))
_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
_MIN_ELEVATION = math.radians(5.0)
# rows of the orbit table (gnss.orbits._ORBIT_FIELDS) and of the clock table (toc, af0, af1, af2, tgd1, tgd2)
_CRS, _DN, _M0, _CUC, _E, _CUS, _SQA, _TOE, _TOE_SOW, _CIC, _OM0, _CIS, _I0, _CRC, _OMEGA, _OMD, _IDOT = (
    range(17)
)
_TOC, _AF0, _AF1, _AF2, _TGD1, _TGD2 = range(6)


@_jit
def _kepler(
    orbit: FloatArray,
    gm: FloatArray,
    we: FloatArray,
    geo: np.ndarray,
    records: np.ndarray,
    times: FloatArray,
    position: FloatArray,
    relativistic: FloatArray,
) -> None:
    """``BroadcastOrbits.position`` of the records ``records`` at ``times``, into ``position`` (n, 3) and
    ``relativistic`` (n,); the Kepler iteration stops when every row's step is below 1e-14 rad."""
    n = records.shape[0]
    mean_anomaly = np.empty(n)
    ecc_anomaly = np.empty(n)
    for row in range(n):
        k = records[row]
        tk = times[row] - orbit[_TOE, k]
        semi_major = orbit[_SQA, k] ** 2
        motion = math.sqrt(gm[k] / semi_major**3) + orbit[_DN, k]
        mean_anomaly[row] = orbit[_M0, k] + motion * tk
        ecc_anomaly[row] = mean_anomaly[row]
    for _ in range(30):
        converged = True
        for row in range(n):
            ecc = orbit[_E, records[row]]
            anomaly = ecc_anomaly[row]
            step = (anomaly - ecc * math.sin(anomaly) - mean_anomaly[row]) / (1.0 - ecc * math.cos(anomaly))
            ecc_anomaly[row] = anomaly - step
            if not abs(step) < 1e-14:
                converged = False
        if converged:
            break
    for row in range(n):
        k = records[row]
        tk = times[row] - orbit[_TOE, k]
        ecc = orbit[_E, k]
        semi_major = orbit[_SQA, k] ** 2
        sin_e, cos_e = math.sin(ecc_anomaly[row]), math.cos(ecc_anomaly[row])
        true_anomaly = math.atan2(math.sqrt(1.0 - ecc * ecc) * sin_e, cos_e - ecc)
        phi = true_anomaly + orbit[_OMEGA, k]
        sin2, cos2 = math.sin(2.0 * phi), math.cos(2.0 * phi)
        u = phi + orbit[_CUS, k] * sin2 + orbit[_CUC, k] * cos2
        r = semi_major * (1.0 - ecc * cos_e) + orbit[_CRS, k] * sin2 + orbit[_CRC, k] * cos2
        inc = orbit[_I0, k] + orbit[_IDOT, k] * tk + orbit[_CIS, k] * sin2 + orbit[_CIC, k] * cos2
        x_orb, y_orb = r * math.cos(u), r * math.sin(u)
        rate = orbit[_OMD, k] if geo[k] else orbit[_OMD, k] - we[k]
        node = orbit[_OM0, k] + rate * tk - we[k] * orbit[_TOE_SOW, k]
        cos_node, sin_node, cos_i = math.cos(node), math.sin(node), math.cos(inc)
        x = x_orb * cos_node - y_orb * cos_i * sin_node
        y = x_orb * sin_node + y_orb * cos_i * cos_node
        z = y_orb * math.sin(inc)
        if geo[k]:  # BDS-SIS-ICD: [X Y Z] = Rz(we tk) Rx(-5 deg) [Xg Yg Zg]
            y1 = _GEO_COS * y + _GEO_SIN * z
            z1 = -_GEO_SIN * y + _GEO_COS * z
            angle = we[k] * tk
            ca, sa = math.cos(angle), math.sin(angle)
            x, y, z = ca * x + sa * y1, -sa * x + ca * y1, z1
        position[row, 0], position[row, 1], position[row, 2] = x, y, z
        relativistic[row] = -2.0 * math.sqrt(gm[k]) / SPEED_OF_LIGHT**2 * ecc * orbit[_SQA, k] * sin_e


@_jit
def _polynomial(clock: FloatArray, k: int, t: float) -> float:
    """af0 + af1 dt + af2 dt^2 with dt = t - toc (``BroadcastOrbits.clock_polynomial``)."""
    dt = t - clock[_TOC, k]
    return float(clock[_AF0, k] + dt * (clock[_AF1, k] + dt * clock[_AF2, k]))


@_jit
def transmit_states_kernel(
    orbit: FloatArray,
    clock: FloatArray,
    gm: FloatArray,
    we: FloatArray,
    geo: np.ndarray,
    records: np.ndarray,
    t_receive: float,
    pseudorange: FloatArray,
    factors: FloatArray,
    position: FloatArray,
    clock_s: FloatArray,
    t_transmit: FloatArray,
    velocity: FloatArray,
    drift: FloatArray,
) -> None:
    """``BroadcastOrbits.transmit_states`` into the arrays after ``factors``: each satellite's transmit time
    from its pseudorange and clock, its orbit there and at +-``VELOCITY_STEP_S`` (one Kepler iteration for
    the three), the clock with the relativistic term and group delay, and the central differences."""
    n = records.shape[0]
    h = VELOCITY_STEP_S
    records3 = np.empty(3 * n, dtype=np.int64)
    times3 = np.empty(3 * n)
    for row in range(n):
        k = records[row]
        t_sv = t_receive - pseudorange[row] / SPEED_OF_LIGHT
        dt = _polynomial(clock, k, t_sv)
        dt = _polynomial(clock, k, t_sv - dt)
        t_tx = t_sv - dt
        t_transmit[row] = t_tx
        records3[row], records3[n + row], records3[2 * n + row] = k, k, k
        times3[row], times3[n + row], times3[2 * n + row] = t_tx, t_tx + h, t_tx - h
    positions = np.empty((3 * n, 3))
    relativistic = np.empty(3 * n)
    _kepler(orbit, gm, we, geo, records3, times3, positions, relativistic)
    for row in range(n):
        k = records[row]
        delay = factors[row, 0] * clock[_TGD1, k] + factors[row, 1] * clock[_TGD2, k]
        clock_s[row] = _polynomial(clock, k, t_transmit[row]) + relativistic[row] - delay
        after = _polynomial(clock, k, times3[n + row]) + relativistic[n + row]
        before = _polynomial(clock, k, times3[2 * n + row]) + relativistic[2 * n + row]
        drift[row] = (after - before) / (2.0 * h)
        for axis in range(3):
            position[row, axis] = positions[row, axis]
            velocity[row, axis] = (positions[n + row, axis] - positions[2 * n + row, axis]) / (2.0 * h)


@_jit
def delays_kernel(
    receiver: FloatArray,
    satellites: FloatArray,
    frequency: FloatArray,
    klobuchar: FloatArray,
    use_klobuchar: bool,
    troposphere: bool,
    gps_seconds: float,
    out: FloatArray,
) -> None:
    """``Atmosphere.delays`` into ``out`` (4, n): ionosphere (m), troposphere (m), elevation and azimuth
    (rad) of each satellite (n, 3) from the ECEF ``receiver`` (3,); ``klobuchar`` the alpha then the beta
    coefficients (8,)."""
    x, y, z = receiver[0], receiver[1], receiver[2]
    # gnss.geodesy.ecef_to_geodetic
    p = math.hypot(x, y)
    lon = math.atan2(y, x)
    beta = math.atan2(WGS84_A * z, WGS84_B * p)
    lat = math.atan2(z + _EP2 * WGS84_B * math.sin(beta) ** 3, p - WGS84_E2 * WGS84_A * math.cos(beta) ** 3)
    for _ in range(4):
        beta = math.atan2((1.0 - WGS84_F) * math.sin(lat), math.cos(lat))
        lat = math.atan2(
            z + _EP2 * WGS84_B * math.sin(beta) ** 3, p - WGS84_E2 * WGS84_A * math.cos(beta) ** 3
        )
    sin_lat, cos_lat = math.sin(lat), math.cos(lat)
    prime_vertical = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    height = p * cos_lat + z * sin_lat - WGS84_A * WGS84_A / prime_vertical
    sin_lon, cos_lon = math.sin(lon), math.cos(lon)
    # gnss.corrections.saastamoinen_zenith in the standard atmosphere (relative humidity 0.7)
    zenith = 0.0
    if troposphere and -1000.0 < height < 1e5:
        top = min(max(height, 0.0), ATMOSPHERE_TOP_M)
        pressure = 1013.25 * (1.0 - 2.2557e-5 * top) ** 5.2568
        temperature = 15.0 - 6.5e-3 * top + 273.16
        vapour = 6.108 * 0.7 * math.exp((17.15 * temperature - 4684.0) / (temperature - 38.45))
        hydrostatic = 0.0022768 * pressure / (1.0 - 0.00266 * math.cos(2.0 * lat) - 0.00028 * top / 1e3)
        zenith = hydrostatic + 0.002277 * (1255.0 / temperature + 0.05) * vapour
    for j in range(satellites.shape[0]):
        dx, dy, dz = satellites[j, 0] - x, satellites[j, 1] - y, satellites[j, 2] - z
        east = -sin_lon * dx + cos_lon * dy
        north = -sin_lat * cos_lon * dx - sin_lat * sin_lon * dy + cos_lat * dz
        up = cos_lat * cos_lon * dx + cos_lat * sin_lon * dy + sin_lat * dz
        elevation = math.atan2(up, math.hypot(east, north))
        azimuth = math.atan2(east, north) % (2.0 * math.pi)
        out[2, j], out[3, j] = elevation, azimuth
        out[1, j] = zenith / math.sin(max(elevation, _MIN_ELEVATION)) if troposphere else 0.0
        if not use_klobuchar:
            out[0, j] = 0.0
            continue
        # gnss.corrections.klobuchar_l1_delay, scaled to the carrier
        el = elevation / math.pi
        psi = 0.0137 / (el + 0.11) - 0.022
        phi_i = min(max(lat / math.pi + psi * math.cos(azimuth), -0.416), 0.416)
        lam_i = lon / math.pi + psi * math.sin(azimuth) / math.cos(phi_i * math.pi)
        phi_m = phi_i + 0.064 * math.cos((lam_i - 1.617) * math.pi)
        local_time = (4.32e4 * lam_i + gps_seconds) % 86400.0
        amplitude = klobuchar[3]
        period = klobuchar[7]
        for power in range(2, -1, -1):
            amplitude = amplitude * phi_m + klobuchar[power]
            period = period * phi_m + klobuchar[4 + power]
        amplitude = max(amplitude, 0.0)
        period = max(period, 72000.0)
        phase = 2.0 * math.pi * (local_time - 50400.0) / period
        obliquity = 1.0 + 16.0 * (0.53 - el) ** 3
        cosine = 1.0 - phase * phase / 2.0 + phase**4 / 24.0
        seconds = obliquity * (5e-9 + (amplitude * cosine if abs(phase) < 1.57 else 0.0))
        out[0, j] = SPEED_OF_LIGHT * seconds * (F_GPS_L1 / frequency[j]) ** 2


def transmit_states(
    orbits: BroadcastOrbits,
    index: np.ndarray,
    t_receive: float,
    pseudorange_m: np.ndarray,
    factors: np.ndarray,
) -> SatelliteStates:
    """``orbits.transmit_states`` by the kernel, or by the numpy reference when the kernels are off."""
    if not compiled_enabled():
        return orbits.transmit_states(index, t_receive, pseudorange_m, factors)
    orbit, clock, gm, we, geo = orbits.kernel_tables
    records = np.asarray(index, dtype=np.int64)
    n = len(records)
    position, velocity = np.empty((n, 3)), np.empty((n, 3))
    clock_s, t_transmit, drift = np.empty(n), np.empty(n), np.empty(n)
    transmit_states_kernel(
        orbit,
        clock,
        gm,
        we,
        geo,
        records,
        float(t_receive),
        np.ascontiguousarray(pseudorange_m, dtype=float),
        np.ascontiguousarray(factors, dtype=float).reshape(n, 2),
        position,
        clock_s,
        t_transmit,
        velocity,
        drift,
    )
    return SatelliteStates(position, clock_s, t_transmit, records, velocity, drift)


def delays(
    atmosphere: Atmosphere, receiver: np.ndarray, prs: PseudorangeSet
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``atmosphere.delays(receiver, prs)`` by the kernel, or by the numpy reference when the kernels are
    off: (ionosphere m, troposphere m, elevation rad, azimuth rad) per row."""
    if not compiled_enabled():
        return atmosphere.delays(receiver, prs)
    coefficients = np.zeros(8)
    if atmosphere.klobuchar is not None:
        alpha, beta = atmosphere.klobuchar
        coefficients[:4], coefficients[4:] = alpha, beta
    out = np.empty((4, len(prs)))
    delays_kernel(
        np.ascontiguousarray(receiver, dtype=float),
        np.ascontiguousarray(prs.sat_position, dtype=float).reshape(len(prs), 3),
        np.ascontiguousarray(prs.frequency_hz, dtype=float),
        coefficients,
        atmosphere.klobuchar is not None,
        atmosphere.troposphere,
        float(prs.gpst),
        out,
    )
    return out[0], out[1], out[2], out[3]


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) both kernels' one signature; returns the seconds."""
    started = time.perf_counter()
    orbit = np.zeros((17, 1))
    orbit[_SQA, 0] = 5153.7
    transmit_states_kernel(
        orbit,
        np.zeros((6, 1)),
        np.array([3.986005e14]),
        np.array([7.2921151467e-5]),
        np.zeros(1, dtype=bool),
        np.zeros(1, dtype=np.int64),
        1.0e5,
        np.array([2.2e7]),
        np.zeros((1, 2)),
        np.empty((1, 3)),
        np.empty(1),
        np.empty(1),
        np.empty((1, 3)),
        np.empty(1),
    )
    delays_kernel(
        np.array([4.0e6, 1.0e5, 4.9e6]),
        np.array([[2.0e7, 1.0e7, 1.5e7]]),
        np.array([F_GPS_L1]),
        np.zeros(8),
        True,
        True,
        1.0e5,
        np.empty((4, 1)),
    )
    return time.perf_counter() - started
