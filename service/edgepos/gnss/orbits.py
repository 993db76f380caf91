"""Satellite position and clock from broadcast Keplerian ephemerides, vectorised over satellites.

Formulas of IS-GPS-200 (table 20-IV, LNAV user algorithm; clock 20.3.3.3.3), BDS-SIS-ICD (section 5.2.4.12,
including the GEO satellites' inertial-to-fixed rotation by -5 degrees about x) and the Galileo OS-SIS-ICD
(identical form). Positions are WGS-84/CGCS2000/GTRF ECEF at the transmit time (the frames agree to
centimetres); :func:`earth_rotation` and :func:`sagnac_range` carry them into the frame of the reception time.
Times are continuous GPS seconds; BeiDou's 14 s offset is already folded into ``toe``/``toc`` by the reader.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.gnss.rinex_nav import KeplerEphemeris

SPEED_OF_LIGHT = 299792458.0
"""m/s."""
OMEGA_EARTH = 7.2921151467e-5
"""WGS-84 Earth rotation rate (rad/s), used for the signal-travel rotation of every system."""
GM = {"G": 3.986005e14, "J": 3.986005e14, "C": 3.986004418e14, "E": 3.986004418e14}
"""Each system's gravitational constant of its ICD (m^3/s^2)."""
OMEGA_E_ICD = {"G": 7.2921151467e-5, "J": 7.2921151467e-5, "C": 7.292115e-5, "E": 7.2921151467e-5}
"""Each system's Earth rotation rate of its ICD (rad/s), used inside the orbit formulas."""
BEIDOU_GEO_PRNS = frozenset({1, 2, 3, 4, 5, 59, 60, 61, 62, 63})
"""BeiDou geostationary satellites, whose broadcast orbit needs the ICD's special rotation."""
MAX_AGE_S = {"G": None, "J": None, "E": 4 * 3600.0, "C": 3 * 3600.0}
"""Largest |t - toe| an ephemeris is used for; None = half the broadcast fit interval (GPS, QZSS)."""
_GEO_TILT = np.deg2rad(-5.0)
_ORBIT_FIELDS = (
    "crs",
    "delta_n",
    "m0",
    "cuc",
    "e",
    "cus",
    "sqrt_a",
    "toe",
    "toe_sow",
    "cic",
    "omega0",
    "cis",
    "i0",
    "crc",
    "omega",
    "omega_dot",
    "idot",
)
"""The record fields the orbit formulas read (``position``), the clock's and group delays' left out."""
VELOCITY_STEP_S = 0.5
"""Half-width (s) of the central difference giving satellite velocity and clock drift. Its truncation error
is h^2/6 times the position's third derivative, about n |a| = 8e-5 m/s^3 for a MEO orbit (mean motion
n = 1.5e-4 rad/s, |a| = 0.6 m/s^2), so 3e-6 m/s; its rounding error, eps |r| / (2h) = 6e-9 m/s, and the
Kepler iteration's 1e-14 rad (3e-7 m over 1 s) are smaller. All are four orders below a Doppler's noise
(about 0.05 m/s), so one step serves every orbit (GEO and IGSO move slower)."""

# Frequencies (Hz) for scaling group delays between bands.
_F_GPS_L1, _F_GPS_L2 = 1575.42e6, 1227.60e6
_F_GAL_E1, _F_GAL_E5A, _F_GAL_E5B = 1575.42e6, 1176.45e6, 1207.14e6
GROUP_DELAY_FACTORS: dict[tuple[str, str], tuple[float, float]] = {
    ("G", "1"): (1.0, 0.0),
    ("J", "1"): (1.0, 0.0),
    ("G", "2"): ((_F_GPS_L1 / _F_GPS_L2) ** 2, 0.0),
    ("C", "2"): (1.0, 0.0),  # B1I: TGD1
    ("C", "7"): (0.0, 1.0),  # B2I: TGD2
    ("C", "6"): (0.0, 0.0),  # B3I: the broadcast clock's reference signal
    ("E", "1"): (1.0, 0.0),  # E1: the BGD of the record's own clock pair (see BroadcastOrbits)
    ("E", "7"): ((_F_GAL_E1 / _F_GAL_E5B) ** 2, 0.0),  # E5b: I/NAV records only (``signal_usable``)
    ("E", "5"): (0.0, (_F_GAL_E1 / _F_GAL_E5A) ** 2),
}
"""(system, RINEX band digit) -> (factor on tgd1, factor on tgd2): seconds subtracted from the clock. For
Galileo, ``BroadcastOrbits`` holds as tgd1 the BGD of each record's own clock pair (I/NAV: E1/E5b, F/NAV:
E1/E5a) and as tgd2 BGD(E1, E5a)."""

GALILEO_E5A_CLOCK = 1 << 8
"""RINEX 3 Galileo "data sources" bit 8: the record's clock (af0-af2) is for the E5a/E1 pair (F/NAV);
bit 9 (or neither, in files that leave the field blank) for E5b/E1 (I/NAV)."""


def group_delay_factors(system: str, code: str) -> tuple[float, float]:
    """Factors of (tgd1, tgd2) for a pseudorange code such as ``C1C`` or ``C2I``; KeyError if unsupported."""
    try:
        return GROUP_DELAY_FACTORS[(system, code[1])]
    except KeyError:
        raise KeyError(f"no broadcast group delay known for system {system} code {code}") from None


@dataclass(frozen=True)
class SatelliteStates:
    """Satellites at their signal transmit time: ECEF positions (n, 3) in the transmit-time frame (m),
    clock offsets (s, relativistic term and group delay included; add ``SPEED_OF_LIGHT * clock_s`` to the
    pseudorange), transmit times (GPS s) and the ephemeris index used per row; ECEF velocities (n, 3) (m/s,
    the rate of change of the Earth-fixed position, same frame as ``position``) and clock drifts (s/s, the
    relativistic term's rate included) at the transmit time."""

    position: np.ndarray
    clock_s: np.ndarray
    t_transmit: np.ndarray
    ephemeris_index: np.ndarray
    velocity: np.ndarray
    clock_drift: np.ndarray


class BroadcastOrbits:
    """All Keplerian ephemerides of a navigation file, stacked as arrays for vectorised evaluation."""

    def __init__(self, ephemerides: Sequence[KeplerEphemeris], healthy_only: bool = True) -> None:
        kept = [e for e in ephemerides if e.system in GM and (e.health == 0 or not healthy_only)]
        self.ephemerides: tuple[KeplerEphemeris, ...] = tuple(kept)
        names = ("toc", "af0", "af1", "af2", *_ORBIT_FIELDS, "tgd1", "tgd2")
        self._a = {n: np.array([getattr(e, n) for e in kept], dtype=float) for n in names}
        # A Galileo record's clock is that of a signal pair, and a single-frequency E1 user subtracts that
        # pair's BGD (Galileo OS SIS ICD 5.1.5): BGD(E1, E5b) with an I/NAV clock, BGD(E1, E5a) with an
        # F/NAV one. F/NAV records broadcast no BGD(E1, E5b) (RINEX leaves it blank, read as 0): taking
        # it for E1 left out up to 3 m of group delay per satellite whenever the nearest record was
        # F/NAV's. tgd1 is therefore the record's own pair's BGD; an E5b user needs an I/NAV record.
        self._e5a_clock = np.array(
            [e.system == "E" and bool(e.data_sources & GALILEO_E5A_CLOCK) for e in kept], dtype=bool
        )
        self._a["tgd1"] = np.where(self._e5a_clock, self._a["tgd2"], self._a["tgd1"])
        # the orbit formulas' fields as rows of one matrix: position() gathers a batch's records with one
        # fancy index instead of one per field
        self._orbit_table = np.array([self._a[n] for n in _ORBIT_FIELDS]).reshape(
            len(_ORBIT_FIELDS), len(kept)
        )
        self._gm = np.array([GM[e.system] for e in kept], dtype=float)
        self._we = np.array([OMEGA_E_ICD[e.system] for e in kept], dtype=float)
        self._geo = np.array([e.system == "C" and e.prn in BEIDOU_GEO_PRNS for e in kept], dtype=bool)
        max_age = []
        for e in kept:
            limit = MAX_AGE_S[e.system]
            max_age.append(e.fit_interval_s / 2.0 if limit is None else limit)
        self._max_age = np.array(max_age, dtype=float)
        # per satellite, its records as (toe, maximum age, index) in file order: plain floats, since
        # select runs every epoch on a handful of records per satellite, where numpy's per-call cost dominates
        self._by_sat: dict[tuple[str, int], list[tuple[float, float, int]]] = {}
        for index, e in enumerate(kept):
            self._by_sat.setdefault((e.system, e.prn), []).append(
                (float(self._a["toe"][index]), float(self._max_age[index]), index)
            )

        self._chosen: dict[tuple[str, int], tuple[float, float, int]] = {}
        """Per satellite, its last choice in ``select`` and the open time interval it holds in."""

    def __len__(self) -> int:
        return len(self.ephemerides)

    @functools.cached_property
    def kernel_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The records as the compiled geometry (``core.measurements.gnss_geometry``) reads them: the orbit
        fields (17, n) in ``_ORBIT_FIELDS`` order, the clock's (6, n: toc, af0, af1, af2, tgd1, tgd2), and
        per record GM, the ICD's Earth rotation rate and whether it is a BeiDou GEO; built once."""
        clock = np.array([self._a[n] for n in ("toc", "af0", "af1", "af2", "tgd1", "tgd2")]).reshape(
            6, len(self.ephemerides)
        )
        return np.ascontiguousarray(self._orbit_table), clock, self._gm, self._we, self._geo

    def select(self, systems: Sequence[str], prns: Sequence[int] | np.ndarray, t: float) -> np.ndarray:
        """Per satellite, the index of the healthy ephemeris whose toe is nearest to ``t`` (GPS s) among those
        within their validity (|t - toe| <= fit interval / 2, or the system's maximum age); -1 if none.

        The choice only changes where a record's validity starts or ends (toe -+ its maximum age) or where
        two toes are equally near (their midpoint); each satellite's last choice is remembered with the
        open interval between those points around the time it was made (less a millisecond each side,
        far beyond the rounding of the ages), and reused for any time inside it: every epoch between two
        such points searches nothing."""
        out: list[int] = []  # a list, then one array: a numpy element written per satellite costs more
        t = float(t)
        numbers = prns.tolist() if isinstance(prns, np.ndarray) else prns
        for system, prn in zip(systems, numbers, strict=True):
            key = (system, int(prn))
            known = self._chosen.get(key)
            if known is not None and known[0] < t < known[1]:
                out.append(known[2])
                continue
            records = self._by_sat.get(key, ())
            best: tuple[float, int] | None = None
            for toe, max_age, index in records:
                age = abs(t - toe)
                # Nearest toe; among equal toes the later record in the file (newest upload) wins.
                if age <= max_age and (best is None or (age, -index) < (best[0], -best[1])):
                    best = (age, index)
            choice = -1 if best is None else best[1]
            self._chosen[key] = (*_stable_interval(records, t), choice)
            out.append(choice)
        return np.array(out, dtype=int).reshape(len(out))

    def clock_polynomial(self, index: np.ndarray, t: np.ndarray) -> np.ndarray:
        """af0 + af1 dt + af2 dt^2 with dt = t - toc (s), without relativity or group delay."""
        a = self._a
        dt = t - a["toc"][index]
        result: np.ndarray = a["af0"][index] + dt * (a["af1"][index] + dt * a["af2"][index])
        return result

    def position(self, index: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ECEF positions (n, 3) at GPS times ``t`` and the relativistic clock term (s) per satellite."""
        a = dict(zip(_ORBIT_FIELDS, self._orbit_table[:, index]))
        gm, we, geo = self._gm[index], self._we[index], self._geo[index]
        tk = np.asarray(t, dtype=float) - a["toe"]
        semi_major = a["sqrt_a"] ** 2
        n = np.sqrt(gm / semi_major**3) + a["delta_n"]
        mean_anomaly = a["m0"] + n * tk
        ecc = a["e"]
        ecc_anomaly = mean_anomaly.copy()
        for _ in range(30):
            step = (ecc_anomaly - ecc * np.sin(ecc_anomaly) - mean_anomaly) / (
                1.0 - ecc * np.cos(ecc_anomaly)
            )
            ecc_anomaly -= step
            if np.all(np.abs(step) < 1e-14):
                break
        sin_e, cos_e = np.sin(ecc_anomaly), np.cos(ecc_anomaly)
        true_anomaly = np.arctan2(np.sqrt(1.0 - ecc * ecc) * sin_e, cos_e - ecc)
        phi = true_anomaly + a["omega"]
        sin2, cos2 = np.sin(2.0 * phi), np.cos(2.0 * phi)
        u = phi + a["cus"] * sin2 + a["cuc"] * cos2
        r = semi_major * (1.0 - ecc * cos_e) + a["crs"] * sin2 + a["crc"] * cos2
        inc = a["i0"] + a["idot"] * tk + a["cis"] * sin2 + a["cic"] * cos2
        x_orb, y_orb = r * np.cos(u), r * np.sin(u)
        node = a["omega0"] + np.where(geo, a["omega_dot"], a["omega_dot"] - we) * tk - we * a["toe_sow"]
        cos_node, sin_node, cos_i = np.cos(node), np.sin(node), np.cos(inc)
        x = x_orb * cos_node - y_orb * cos_i * sin_node
        y = x_orb * sin_node + y_orb * cos_i * cos_node
        z = y_orb * np.sin(inc)
        if geo.any():
            # BDS-SIS-ICD: [X Y Z] = Rz(we tk) Rx(-5 deg) [Xg Yg Zg] for GEO satellites.
            c5, s5 = np.cos(_GEO_TILT), np.sin(_GEO_TILT)
            y1 = c5 * y + s5 * z
            z1 = -s5 * y + c5 * z
            angle = we * tk
            ca, sa = np.cos(angle), np.sin(angle)
            x_geo = ca * x + sa * y1
            y_geo = -sa * x + ca * y1
            x, y, z = np.where(geo, x_geo, x), np.where(geo, y_geo, y), np.where(geo, z1, z)
        relativistic = -2.0 * np.sqrt(gm) / SPEED_OF_LIGHT**2 * ecc * a["sqrt_a"] * sin_e
        return np.stack([x, y, z], axis=-1), relativistic

    def signal_usable(self, index: int, system: str, code: str) -> bool:
        """Whether record ``index`` gives the clock of ``system``'s signal ``code``: a Galileo E5b code
        (band 7) needs the BGD(E1, E5b) that only an I/NAV record broadcasts; every other signal with a
        group-delay rule any record of its system."""
        return not (system == "E" and code[1] == "7" and bool(self._e5a_clock[index]))

    def group_delay(self, index: np.ndarray, factors: np.ndarray) -> np.ndarray:
        """Broadcast group delay (s) per row, from (n, 2) factors on (tgd1, tgd2)."""
        result: np.ndarray = factors[:, 0] * self._a["tgd1"][index] + factors[:, 1] * self._a["tgd2"][index]
        return result

    def transmit_states(
        self, index: np.ndarray, t_receive: float, pseudorange_m: np.ndarray, delay_factors: np.ndarray
    ) -> SatelliteStates:
        """Satellite positions and clocks at the true transmit time of each pseudorange.

        The satellite's transmit time in its own clock is t_receive - P/c (the receiver clock error cancels);
        the satellite clock correction (IS-GPS-200 20.3.3.3.3.1) turns it into system time.
        """
        index = np.asarray(index, dtype=int)
        t_sv = t_receive - np.asarray(pseudorange_m, dtype=float) / SPEED_OF_LIGHT
        dt = self.clock_polynomial(index, t_sv)
        dt = self.clock_polynomial(index, t_sv - dt)
        t_tx = t_sv - dt
        # the transmit time and the two of the rates' central difference (:meth:`rates`) in one evaluation
        n, h = len(index), VELOCITY_STEP_S
        index3 = np.concatenate([index, index, index])
        t3 = np.concatenate([t_tx, t_tx + h, t_tx - h])
        positions, relativistic3 = self.position(index3, t3)
        clocks = self.clock_polynomial(index3, t3) + relativistic3
        position, relativistic = positions[:n], relativistic3[:n]
        clock = self.clock_polynomial(index, t_tx) + relativistic - self.group_delay(index, delay_factors)
        velocity = (positions[n : 2 * n] - positions[2 * n :]) / (2.0 * h)
        drift = (clocks[n : 2 * n] - clocks[2 * n :]) / (2.0 * h)
        return SatelliteStates(position, clock, t_tx, index, velocity, drift)

    def rates(self, index: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ECEF velocity (n, 3) (m/s) and clock drift (s/s, relativistic rate included) at GPS times ``t``.

        Central difference of :meth:`position` and the clock over +-``VELOCITY_STEP_S`` (see its note for the
        error budget): one code path for every orbit type, the BeiDou GEO rotation included, rather than a
        second, analytic copy of the orbit formulas to keep consistent with the first."""
        index = np.asarray(index, dtype=int)
        t = np.asarray(t, dtype=float)
        h = VELOCITY_STEP_S
        after, rel_after = self.position(index, t + h)
        before, rel_before = self.position(index, t - h)
        clock_after = self.clock_polynomial(index, t + h) + rel_after
        clock_before = self.clock_polynomial(index, t - h) + rel_before
        return (after - before) / (2.0 * h), (clock_after - clock_before) / (2.0 * h)


def earth_rotation(position: np.ndarray, travel_time_s: np.ndarray | float) -> np.ndarray:
    """Rotate ECEF positions (..., 3) of the transmit time into the ECEF frame of the reception time."""
    angle = OMEGA_EARTH * np.asarray(travel_time_s, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = position[..., 0], position[..., 1], position[..., 2]
    return np.stack([c * x + s * y, -s * x + c * y, z], axis=-1)


def sagnac_range(satellite: np.ndarray, receiver: np.ndarray) -> np.ndarray:
    """Geometric range (m) from receiver to satellite including the Earth-rotation (Sagnac) term.

    ``satellite`` (..., 3) at transmit time, ``receiver`` (..., 3) at reception time, both ECEF and
    broadcastable; rho = |s - r| + omega_e (x_s y_r - y_s x_r) / c, good to millimetres for GNSS orbits.
    """
    diff = satellite - receiver
    geometric = np.sqrt(np.sum(diff * diff, axis=-1))
    sagnac = OMEGA_EARTH * (satellite[..., 0] * receiver[..., 1] - satellite[..., 1] * receiver[..., 0])
    result: np.ndarray = geometric + sagnac / SPEED_OF_LIGHT
    return result


def sagnac_range_rate(
    sat_position: np.ndarray, sat_velocity: np.ndarray, receiver: np.ndarray, receiver_velocity: np.ndarray
) -> np.ndarray:
    """Geometric range rate (m/s) with the Sagnac term's rate, the time derivative of :func:`sagnac_range`.

    Satellite (..., 3) position and velocity at transmit time, receiver (..., 3) position and velocity at
    reception, all ECEF and broadcastable."""
    diff = sat_position - receiver
    distance = np.sqrt(np.sum(diff * diff, axis=-1))
    relative = sat_velocity - receiver_velocity
    geometric = np.sum(diff * relative, axis=-1) / distance
    sagnac = OMEGA_EARTH * (
        sat_velocity[..., 0] * receiver[..., 1]
        + sat_position[..., 0] * receiver_velocity[..., 1]
        - sat_velocity[..., 1] * receiver[..., 0]
        - sat_position[..., 1] * receiver_velocity[..., 0]
    )
    result: np.ndarray = geometric + sagnac / SPEED_OF_LIGHT
    return result


_CHOICE_MARGIN_S = 1e-3
"""How far inside the points where a satellite's ephemeris choice may change ``select`` reuses it (s)."""


def _stable_interval(records: Sequence[tuple[float, float, int]], t: float) -> tuple[float, float]:
    """The open interval around ``t`` in which ``select``'s choice among ``records`` (toe, maximum age,
    index) cannot change: between the nearest of the records' validity edges and toe midpoints on either
    side, each less ``_CHOICE_MARGIN_S``; empty (t, t) when ``t`` is that close to one."""
    points = [toe + sign * max_age for toe, max_age, _ in records for sign in (-1.0, 1.0)]
    points += [0.5 * (a[0] + b[0]) for k, a in enumerate(records) for b in records[k + 1 :] if a[0] != b[0]]
    below = max((p for p in points if p <= t), default=-math.inf) + _CHOICE_MARGIN_S
    above = min((p for p in points if p >= t), default=math.inf) - _CHOICE_MARGIN_S
    return (below, above) if below < t < above else (t, t)
