"""Pseudorange sets with their satellites' transmit-time states, and the atmospheric part of the range model.

This is the seam between the readers/orbits and any estimator: :func:`prepare_epoch` turns an observation
epoch into a :class:`PseudorangeSet` (what the future ``pseudorange`` measurement carries, satellite position
and clock included), and :class:`Atmosphere` gives the ionosphere and troposphere delays for a receiver
position. Estimators (the WLS baseline here, filters elsewhere) only add geometry and clock bias.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.gnss.corrections import carrier_frequency, klobuchar_delay, saastamoinen_delay
from edgepos.gnss.geodesy import ecef_to_geodetic, elevation_azimuth
from edgepos.gnss.orbits import SPEED_OF_LIGHT, BroadcastOrbits, group_delay_factors
from edgepos.gnss.rinex_nav import NavigationData
from edgepos.gnss.rinex_obs import DEFAULT_CODES, ObservationEpoch

GALILEO_GROUP_DELAYS = ("broadcast", "none")
"""What a receiver's Galileo code carries of the satellite's group delay. broadcast: the Galileo ICD's model,
the clock less the BGD of the record's clock pair (``BroadcastOrbits``); none: the clock without it, for
receivers whose Galileo code measures as if the satellite had none."""
DEFAULT_GALILEO_GROUP_DELAY = "none"
"""The vehicle's receiver, chosen on the first half of tests/data/gnss-rover (a Septentrio mosaic-X5): its
Galileo residuals at the reference are smaller without the BGD (docs/gnss.md, "The receivers' Galileo group
delay")."""

STATION_GALILEO_GROUP_DELAY = "broadcast"
"""A reference station receiver's unless registered otherwise: the ICD's, as the recording's station (a Leica
GR50) measures (docs/gnss.md, "The receivers' Galileo group delay")."""


def without_group_delay(galileo_group_delay: str) -> frozenset[str]:
    """The systems whose receiver code is modelled without the satellite group delay."""
    if galileo_group_delay not in GALILEO_GROUP_DELAYS:
        raise ValueError(
            f"galileo group delay must be one of {GALILEO_GROUP_DELAYS}, not {galileo_group_delay!r}"
        )
    return frozenset({"E"}) if galileo_group_delay == "none" else frozenset()


@dataclass(frozen=True)
class PseudorangeSet:
    """One epoch's usable pseudoranges (n rows) with satellite ECEF positions at transmit time (m, in the
    transmit-time frame), satellite clock offsets (s; add c * clock to the pseudorange) and carriers (Hz).

    Optional, for Doppler: measured range rates (m/s, -lambda times the RINEX Doppler; NaN where a row has
    none), the satellites' ECEF velocities (m/s) and clock drifts (s/s; NaN where unknown). All three are
    None when the epoch carries no Doppler at all."""

    gpst: float
    systems: tuple[str, ...]
    prns: np.ndarray
    pseudorange_m: np.ndarray
    cn0_dbhz: np.ndarray
    sat_position: np.ndarray
    sat_clock_s: np.ndarray
    frequency_hz: np.ndarray
    range_rate_mps: np.ndarray | None = None
    sat_velocity: np.ndarray | None = None
    sat_clock_drift: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.systems)

    @functools.cached_property
    def sats(self) -> tuple[str, ...]:
        """RINEX satellite identifiers per row (formatted once per set: gnss_tight reads them per row)."""
        return tuple(f"{s}{int(p):02d}" for s, p in zip(self.systems, self.prns))

    def subset(self, keep: np.ndarray) -> PseudorangeSet:
        """Rows where the boolean ``keep`` is true."""
        rows = np.flatnonzero(keep)
        return PseudorangeSet(
            self.gpst,
            tuple(self.systems[i] for i in rows),
            self.prns[rows],
            self.pseudorange_m[rows],
            self.cn0_dbhz[rows],
            self.sat_position[rows],
            self.sat_clock_s[rows],
            self.frequency_hz[rows],
            None if self.range_rate_mps is None else self.range_rate_mps[rows],
            None if self.sat_velocity is None else self.sat_velocity[rows],
            None if self.sat_clock_drift is None else self.sat_clock_drift[rows],
        )

    @property
    def has_doppler(self) -> bool:
        """Whether any row has a range rate with its satellite's velocity and clock drift."""
        if self.range_rate_mps is None or self.sat_velocity is None or self.sat_clock_drift is None:
            return False
        return bool(np.any(np.isfinite(self.range_rate_mps) & np.isfinite(self.sat_clock_drift)))


def doppler_to_range_rate(doppler_hz: np.ndarray, frequency_hz: np.ndarray) -> np.ndarray:
    """Range rate (m/s) of Dopplers (Hz, RINEX sign: positive when the satellite approaches) on carriers (Hz):
    -D c / f."""
    result: np.ndarray = (
        -np.asarray(doppler_hz, dtype=float) * SPEED_OF_LIGHT / np.asarray(frequency_hz, dtype=float)
    )
    return result


def prepare_epoch(
    epoch: ObservationEpoch,
    orbits: BroadcastOrbits,
    codes: Mapping[str, tuple[str, str]] | None = None,
    no_group_delay: frozenset[str] = frozenset(),
) -> tuple[PseudorangeSet, tuple[str, ...]]:
    """Compute satellite states for an epoch's pseudoranges; return the set and the satellites dropped for
    lack of a valid ephemeris, of a group-delay rule for their signal (or for their signal with the chosen
    record: ``BroadcastOrbits.signal_usable``), or because ``codes`` omits their system. The systems of
    ``no_group_delay`` (:func:`without_group_delay`) get their clocks without the broadcast group delay."""
    chosen = dict(DEFAULT_CODES if codes is None else codes)
    index = orbits.select(epoch.systems, epoch.prns, epoch.gpst)
    factors = np.zeros((len(epoch), 2))
    frequency = np.zeros(len(epoch))
    usable = index >= 0
    for row, system in enumerate(epoch.systems):
        if system not in chosen:
            usable[row] = False
            continue
        code = chosen[system][0]
        try:
            delay = group_delay_factors(system, code)
            frequency[row] = carrier_frequency(system, code)
        except KeyError:
            usable[row] = False
            continue
        if system in no_group_delay:
            continue  # factors stay zero
        factors[row] = delay
        if usable[row] and not orbits.signal_usable(int(index[row]), system, code):
            usable[row] = False
    dropped = tuple(s for s, ok in zip(epoch.sats, usable) if not ok)
    rows = np.flatnonzero(usable)
    states = orbits.transmit_states(index[rows], epoch.gpst, epoch.pseudorange_m[rows], factors[rows])
    range_rate = doppler_to_range_rate(epoch.doppler_hz[rows], frequency[rows])
    doppler = bool(np.any(np.isfinite(range_rate)))
    prepared = PseudorangeSet(
        epoch.gpst,
        tuple(epoch.systems[i] for i in rows),
        epoch.prns[rows],
        epoch.pseudorange_m[rows],
        epoch.cn0_dbhz[rows],
        states.position,
        states.clock_s,
        frequency[rows],
        range_rate if doppler else None,
        states.velocity if doppler else None,
        states.clock_drift if doppler else None,
    )
    return prepared, dropped


@dataclass(frozen=True)
class Atmosphere:
    """Broadcast ionosphere (Klobuchar alpha/beta or None to switch it off) and Saastamoinen troposphere."""

    klobuchar: tuple[Sequence[float], Sequence[float]] | None
    troposphere: bool = True

    @classmethod
    def from_navigation(cls, nav: NavigationData, troposphere: bool = True) -> Atmosphere:
        """The GPS Klobuchar set of a navigation header (None when the header lacks it)."""
        return cls(nav.klobuchar_gps, troposphere)

    def delays(
        self, receiver: np.ndarray, prs: PseudorangeSet
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(ionosphere m, troposphere m, elevation rad, azimuth rad) per row for an ECEF receiver position."""
        lat, lon, height = (float(v) for v in ecef_to_geodetic(receiver))
        elevation, azimuth = elevation_azimuth(receiver, prs.sat_position)
        if self.klobuchar is None:
            iono = np.zeros(len(prs))
        else:
            alpha, beta = self.klobuchar
            iono = klobuchar_delay(alpha, beta, lat, lon, elevation, azimuth, prs.gpst, prs.frequency_hz)
        tropo = saastamoinen_delay(lat, height, elevation) if self.troposphere else np.zeros(len(prs))
        return iono, tropo, elevation, azimuth
