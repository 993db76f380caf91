"""Differential pseudorange corrections from a reference station at a known position (code DGNSS).

For each base epoch and satellite above the mask, the correction is what the range model predicts at the
base's known position minus what the base measured, with the base's receiver clock removed:

    C = rho_sagnac(base) + I_model + T_model - c dt_sat - P_base - clock_base(system)

``clock_base`` is the per-system median over the epoch's satellites of the same difference (a receiver
clock is common to all of a system's satellites; the median ignores a multipath outlier). ``C`` thus holds
what the models got wrong at the base - broadcast orbit and clock errors, the Klobuchar and Saastamoinen
models' errors - which at 14 km is nearly the same at the rover. The rover keeps its own models and adds
``C``: it still applies Klobuchar and Saastamoinen at its own position, so the correction removes only their
error, and the height difference between base and rover (the troposphere's main gradient) stays modelled.
A rover that models no ionosphere (or troposphere) adds the base's modelled term too (:meth:`lookup`
returns them), which removes the whole delay as measured at the base.

A correction is held, not propagated, between its base epoch and the rover's: range-rate corrections
from the base's Doppler (the same difference for range rates) were tried, and propagating by them made the
correction's prediction worse than holding it at every age measured (1-120 s; docs/gnss.md): the Doppler's
noise times the age exceeds the correction's own slow change.

Which correction a rover pseudorange gets: the newest of its satellite at or before the rover epoch
(never a later one: a live site has no future base epoch, so neither does the evaluation), only when no
older than ``max_age_s`` and computed with the same broadcast ephemeris (issue = IODE and toe) as the
rover's, since a correction removes the error of one particular orbit and clock set.
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.gnss.geodesy import ecef_to_geodetic, enu_rotation
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet, prepare_epoch
from edgepos.gnss.orbits import SPEED_OF_LIGHT, BroadcastOrbits, sagnac_range
from edgepos.gnss.rinex_obs import ObservationEpoch, ObservationHeader

DEFAULT_MAX_AGE_S = 30.0
"""Default maximum correction age (s); see docs/gnss.md for the measurement behind it."""

Issue = tuple[int, float]
"""The broadcast ephemeris a correction was computed with: (IODE, toe in GPS seconds). IODE alone is not an
issue number for BeiDou (AODE is an age), so the toe is part of the key."""

NO_CORRECTION = "no correction for this satellite"
TOO_OLD = "correction too old"
ISSUE_MISMATCH = "ephemeris issue mismatch"
SYSTEM_NOT_CORRECTED = "its constellation is not among the session's correction_systems"


def ephemeris_issues(orbits: BroadcastOrbits, index: np.ndarray) -> list[Issue | None]:
    """The issue key of each selected ephemeris index (None where the index is -1)."""
    table = _ISSUES.get(orbits)
    if table is None:  # once per set of ephemerides (their tuple never changes), not per row and epoch
        table = [(int(e.iode), float(e.toe)) for e in orbits.ephemerides]
        _ISSUES[orbits] = table
    return [None if i < 0 else table[i] for i in np.asarray(index).tolist()]


_ISSUES: weakref.WeakKeyDictionary[BroadcastOrbits, list[Issue]] = weakref.WeakKeyDictionary()
"""Per set of broadcast orbits (while it lives), every record's issue key in record order."""


def base_position(header: ObservationHeader) -> np.ndarray:
    """The antenna reference point of a station's RINEX header (m, ECEF): ``APPROX POSITION XYZ`` (the
    marker) plus ``ANTENNA: DELTA H/E/N`` rotated from up/east/north. Raises ValueError without a position."""
    if header.approx_position is None or not np.all(np.isfinite(header.approx_position)):
        raise ValueError("the base station's RINEX header has no APPROX POSITION XYZ")
    marker = np.asarray(header.approx_position, dtype=float)
    if np.linalg.norm(marker) < 6.0e6:
        raise ValueError("the base station's APPROX POSITION XYZ is not on the Earth's surface")
    if header.antenna_delta_hen is None:
        return marker
    up, east, north = header.antenna_delta_hen
    lat, lon, _ = ecef_to_geodetic(marker)
    result: np.ndarray = marker + enu_rotation(float(lat), float(lon)).T @ np.array([east, north, up])
    return result


def _issue(issue: Issue | None) -> Issue:
    if issue is None:  # prepare_epoch keeps only satellites with a selected ephemeris
        raise ValueError("a prepared satellite without an ephemeris")
    return issue


@dataclass(frozen=True)
class EpochCorrections:
    """One base epoch's corrections: per satellite (``sats``) the pseudorange correction (m), the ephemeris
    issue used, and the modelled ionosphere and troposphere at the
    base (m)."""

    gpst: float
    sats: tuple[str, ...]
    correction_m: np.ndarray
    issues: tuple[Issue, ...]
    ionosphere_m: np.ndarray
    troposphere_m: np.ndarray


def epoch_corrections(
    epoch: ObservationEpoch,
    position: np.ndarray,
    orbits: BroadcastOrbits,
    atmosphere: Atmosphere,
    codes: Mapping[str, tuple[str, str]] | None = None,
    elevation_mask_rad: float = np.radians(10.0),
    no_group_delay: frozenset[str] = frozenset(),
) -> EpochCorrections:
    """Corrections of one base epoch at the base's known ECEF ``position`` (m). Satellites below the mask,
    without an ephemeris or alone in their system (no clock to remove) get none. The station receiver's
    code of the systems in ``no_group_delay`` carries no satellite group delay (``gnss.measurements``)."""
    position = np.asarray(position, dtype=float)
    prs, _ = prepare_epoch(epoch, orbits, codes, no_group_delay)
    if len(prs) == 0:
        empty = np.zeros(0)
        return EpochCorrections(epoch.gpst, (), empty, (), empty, empty)
    issues = ephemeris_issues(orbits, orbits.select(prs.systems, prs.prns, prs.gpst))
    iono, tropo, elevation, _ = atmosphere.delays(position, prs)
    model = sagnac_range(prs.sat_position, position) + iono + tropo - SPEED_OF_LIGHT * prs.sat_clock_s
    raw = model - prs.pseudorange_m
    systems = np.array(prs.systems)
    keep = (elevation >= elevation_mask_rad) & np.isfinite(raw)
    correction = np.full(len(prs), np.nan)
    for system in set(prs.systems):
        rows = keep & (systems == system)
        if rows.sum() < 2:
            keep &= systems != system
            continue
        correction[rows] = raw[rows] - np.median(raw[rows])
    rows = np.flatnonzero(keep)
    sats = prs.sats
    return EpochCorrections(
        epoch.gpst,
        tuple(sats[r] for r in rows),
        correction[rows],
        tuple(_issue(issues[r]) for r in rows),
        iono[rows],
        tropo[rows],
    )


@dataclass(frozen=True)
class Correction:
    """A correction ready to add to a rover pseudorange at one epoch (m), its age (s), and the base's
    modelled ionosphere and troposphere (m) for a rover that does not model them."""

    value_m: float
    age_s: float
    ionosphere_m: float
    troposphere_m: float


MAX_AGE_BOUNDS_S = (1.0, 600.0)


class CorrectionTable:
    """Every base epoch's corrections, indexed per satellite for the rover's lookups, and how old (s) a
    correction may be and still apply: a property of the site's correction source, not of a session."""

    def __init__(
        self,
        epochs: Iterable[EpochCorrections],
        max_age_s: float = DEFAULT_MAX_AGE_S,
        no_data_reason: str | None = None,
    ) -> None:
        """``no_data_reason``: what :meth:`lookup` answers when the table holds no correction at all (the
        service says which station had no data, and why), instead of NO_CORRECTION."""
        low, high = MAX_AGE_BOUNDS_S
        if not low <= max_age_s <= high:  # also refuses NaN
            raise ValueError(
                f"the maximum correction age must be in [{low:g}, {high:g}] s, got {max_age_s!r}"
            )
        self.max_age_s = float(max_age_s)
        self.no_data_reason = no_data_reason
        per_sat: dict[str, list[tuple[float, float, Issue, float, float]]] = {}
        for e in epochs:
            for k, sat in enumerate(e.sats):
                per_sat.setdefault(sat, []).append(
                    (
                        e.gpst,
                        float(e.correction_m[k]),
                        e.issues[k],
                        float(e.ionosphere_m[k]),
                        float(e.troposphere_m[k]),
                    )
                )
        self._times: dict[str, np.ndarray] = {}
        self._rows: dict[str, list[tuple[float, float, Issue, float, float]]] = {}
        for sat, rows in per_sat.items():
            rows.sort(key=lambda row: row[0])
            self._rows[sat] = rows
            self._times[sat] = np.array([row[0] for row in rows])

    def __len__(self) -> int:
        return sum(len(rows) for rows in self._rows.values())

    @property
    def satellites(self) -> list[str]:
        return sorted(self._rows)

    def lookup(self, sat: str, issue: Issue | None, gpst: float, max_age_s: float) -> Correction | str:
        """The correction for ``sat`` at rover time ``gpst`` (GPS s) computed with ephemeris ``issue``, or
        why there is none (a sentence starting with NO_CORRECTION, TOO_OLD or ISSUE_MISMATCH)."""
        times = self._times.get(sat)
        if times is None:
            return self.no_data_reason if (self.no_data_reason and not self._times) else NO_CORRECTION
        k = int(np.searchsorted(times, gpst + 1e-6, side="right")) - 1
        if k < 0:
            return f"{NO_CORRECTION} at or before this epoch"
        t_base, value, base_issue, iono, tropo = self._rows[sat][k]
        age = gpst - t_base
        if age > max_age_s:
            return f"{TOO_OLD}: {age:.1f} s > the maximum correction age {max_age_s:g} s"
        if issue is None or base_issue != issue:
            rover = "none" if issue is None else f"IODE {issue[0]} toe {issue[1]:.0f}"
            return f"{ISSUE_MISMATCH}: base IODE {base_issue[0]} toe {base_issue[1]:.0f}, rover {rover}"
        return Correction(value, age, iono, tropo)


def corrections_from_epochs(
    epochs: Iterable[ObservationEpoch],
    position: np.ndarray,
    orbits: BroadcastOrbits,
    atmosphere: Atmosphere,
    codes: Mapping[str, tuple[str, str]] | None = None,
    elevation_mask_rad: float = np.radians(10.0),
    max_age_s: float = DEFAULT_MAX_AGE_S,
    no_group_delay: frozenset[str] = frozenset(),
) -> CorrectionTable:
    """A correction table from a base station's observation epochs at its known ECEF position (m)."""
    return CorrectionTable(
        (
            epoch_corrections(e, position, orbits, atmosphere, codes, elevation_mask_rad, no_group_delay)
            for e in epochs
        ),
        max_age_s,
    )


def apply_corrections(
    table: CorrectionTable,
    sats: Sequence[str],
    issues: Sequence[Issue | None],
    gpst: float,
    max_age_s: float,
    ionosphere_modelled: bool = True,
    troposphere_modelled: bool = True,
) -> tuple[np.ndarray, list[str | None]]:
    """Per rover pseudorange: the amount to add (m; NaN where none applies) and why none applies (None
    where one does). Adds the base's modelled ionosphere / troposphere when the rover does not model them."""
    delta = np.full(len(sats), np.nan)
    reasons: list[str | None] = []
    for row, (sat, issue) in enumerate(zip(sats, issues)):
        found = table.lookup(sat, issue, gpst, max_age_s)
        if isinstance(found, str):
            reasons.append(found)
            continue
        value = found.value_m
        if not ionosphere_modelled:
            value += found.ionosphere_m
        if not troposphere_modelled:
            value += found.troposphere_m
        delta[row] = value
        reasons.append(None)
    return delta, reasons


def correct_set(
    prs: PseudorangeSet,
    orbits: BroadcastOrbits,
    table: CorrectionTable,
    max_age_s: float,
    ionosphere_modelled: bool = True,
    troposphere_modelled: bool = True,
    systems: Collection[str] | None = None,
) -> tuple[PseudorangeSet, np.ndarray, list[str | None]]:
    """A rover epoch's pseudoranges with the corrections added where one applies (the others unchanged),
    the boolean mask of corrected rows and, per row, why no correction applies (None where one does). The
    ephemeris issue of each row is the one ``orbits.select`` picks, as ``prepare_epoch`` did. With
    ``systems``, only those constellations' rows are corrected (a gnss_tight session's
    ``correction_systems``)."""
    issues = ephemeris_issues(orbits, orbits.select(prs.systems, prs.prns, prs.gpst))
    delta, reasons = apply_corrections(
        table, prs.sats, issues, prs.gpst, max_age_s, ionosphere_modelled, troposphere_modelled
    )
    if systems is not None:
        for row, system in enumerate(prs.systems):
            if system not in systems:
                delta[row], reasons[row] = np.nan, SYSTEM_NOT_CORRECTED
    applied = np.isfinite(delta)
    corrected = prs.pseudorange_m + np.where(applied, delta, 0.0)
    return dataclasses.replace(prs, pseudorange_m=corrected), applied, reasons
