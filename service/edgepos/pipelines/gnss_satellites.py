"""The satellites of a ``gnss_tight`` epoch: each pseudorange's satellite state (from the client or the
broadcast ephemerides), its Doppler as a range rate, the differential correction of the site's reference
station where one applies, and the atmosphere models, with the reason for every measurement left out.
Split from ``gnss_tight`` (the filter step stays there); pure numpy, no web imports."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.measurements.gnss_geometry import transmit_states
from edgepos.core.observations import Observation, PseudorangeObservation
from edgepos.gnss.carrier import CarrierTable, HatchConfig, hatch_update
from edgepos.gnss.corrections import carrier_frequency
from edgepos.gnss.differential import SYSTEM_NOT_CORRECTED, CorrectionTable, Issue, ephemeris_issues
from edgepos.gnss.ephemerides import DEFAULT_SIGNAL, Ephemerides
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet, doppler_to_range_rate, without_group_delay
from edgepos.gnss.orbits import SPEED_OF_LIGHT, group_delay_factors
from edgepos.gnss.timesys import SECONDS_PER_WEEK
from edgepos.pipelines.base import MeasurementUse
from edgepos.pipelines.gnss_carrier_kernel import hatch_kernel
from edgepos.pipelines.gnss_session import GnssSession

CorrectionUses = dict[int, tuple[bool, str | None]]
"""Per observation index: whether a differential correction was added, and why not (None when it was)."""


@dataclass(frozen=True)
class EpochSatellites:
    """The epoch's usable pseudoranges (rows of ``prs``) and the observation index of each row; with Doppler,
    ``prs`` carries range rates (NaN where a row has none or no satellite velocity), and ``doppler_reasons``
    says why a sent Doppler cannot be used whatever the filter does."""

    prs: PseudorangeSet
    indices: list[int]
    doppler_reasons: dict[int, str]
    issues: list[Issue | None] = dataclasses.field(default_factory=list)
    """Per row, the broadcast ephemeris issue its satellite state came from (None: sent by the client)."""
    corrected: np.ndarray | None = None
    """Per row, whether a differential correction was added to its pseudorange (None: no corrections)."""
    phases: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    """Per row, :func:`epoch_phases` (carrier, Doppler, LLI) when carrier smoothing has read them (None: not
    read), so that the phase differences (pipelines/gnss_tdcp.py) do not read them again."""


_FREQUENCY = {system: carrier_frequency(system, code) for system, code in DEFAULT_SIGNAL.items()}
_DELAY_FACTORS = {system: group_delay_factors(system, code) for system, code in DEFAULT_SIGNAL.items()}
"""Per system, the carrier (Hz) and group-delay factors of its default signal, looked up once."""
_NO_DELAY = (0.0, 0.0)

NO_SAT_VELOCITY = (
    "no satellite velocity: with sat_position and sat_clock sent the service computes no orbit, and the "
    "range-rate model needs the satellite's velocity and clock drift (send sat_velocity and sat_clock_drift)"
)


def epoch_satellites(
    epoch: list[int],
    observations: Sequence[Observation],
    ephemerides: Ephemerides | None,
    gpst: float,
    options: Mapping[str, Any],
    uses: dict[int, MeasurementUse],
) -> EpochSatellites:
    """Satellite states per pseudorange, from the client or the broadcast ephemerides; reasons for the rest."""
    rows: list[tuple[Any, ...]] = []
    need_orbit: list[int] = []
    orbit_observations: list[PseudorangeObservation] = []  # observations[i] for i in need_orbit, narrowed
    use_doppler = bool(options.get("use_doppler", True))
    doppler_reasons: dict[int, str] = {}
    nan3 = np.full(3, np.nan)
    orbit_rows: _Columns | None = None
    for i in epoch:
        observation = observations[i]
        if not isinstance(observation, PseudorangeObservation):
            continue
        if observation.doppler_hz is not None and not use_doppler:
            doppler_reasons[i] = "options.use_doppler is off"
        if observation.system not in options["systems"]:
            uses[i] = MeasurementUse(
                i, observation.kind, False, f"system {observation.system} is not in options.systems"
            )
            continue
        if observation.cn0 < options["min_cn0"]:
            uses[i] = MeasurementUse(
                i, observation.kind, False, f"C/N0 below options.min_cn0 ({options['min_cn0']:g} dB-Hz)"
            )
            continue
        if observation.sat_position is not None and observation.sat_clock is not None:
            frequency = carrier_frequency(observation.system, DEFAULT_SIGNAL[observation.system])
            row_rate, row_velocity, row_drift = math.nan, nan3, math.nan
            if observation.doppler_hz is not None and i not in doppler_reasons:
                if observation.sat_velocity is None or observation.sat_clock_drift is None:
                    doppler_reasons[i] = NO_SAT_VELOCITY
                else:
                    row_rate = float(
                        doppler_to_range_rate(np.array([observation.doppler_hz]), np.array([frequency]))[0]
                    )
                    row_velocity = np.asarray(observation.sat_velocity, float)
                    row_drift = observation.sat_clock_drift
            rows.append(
                (
                    i,
                    observation.system,
                    observation.prn,
                    observation.pseudorange,
                    observation.cn0,
                    np.asarray(observation.sat_position, float),
                    observation.sat_clock,
                    frequency,
                    row_rate,
                    row_velocity,
                    row_drift,
                    None,
                )
            )
        else:
            need_orbit.append(i)
            orbit_observations.append(observation)
    if need_orbit:
        if ephemerides is None:
            for i in need_orbit:
                uses[i] = MeasurementUse(
                    i,
                    "pseudorange",
                    False,
                    "no ephemerides loaded (PUT /v1/ephemerides) and no sat_position/sat_clock sent",
                )
        else:
            observed = orbit_observations
            systems = [o.system for o in observed]
            prns = np.array([o.prn for o in observed])
            ephemeris_index = ephemerides.orbits.select(systems, prns, gpst)
            issues = ephemeris_issues(ephemerides.orbits, ephemeris_index)
            have = np.flatnonzero(ephemeris_index >= 0)
            for row in np.flatnonzero(ephemeris_index < 0):
                o = observed[row]
                uses[need_orbit[row]] = MeasurementUse(
                    need_orbit[row],
                    "pseudorange",
                    False,
                    f"no valid healthy ephemeris for {o.system}{o.prn:02d} at GPS week {int(gpst // SECONDS_PER_WEEK)} "
                    f"second {gpst % SECONDS_PER_WEEK:.1f}",
                )
            if have.size:
                orbit_rows = _orbit_rows(
                    ephemerides,
                    observed,
                    systems,
                    need_orbit,
                    ephemeris_index,
                    issues,
                    have,
                    gpst,
                    use_doppler,
                    without_group_delay(options.get("galileo_group_delay", "broadcast")),
                )
    if orbit_rows is not None and not rows:  # every satellite from the orbits: nothing to merge
        columns = orbit_rows
    else:
        columns = _client_rows(rows)
        if orbit_rows is not None:
            columns = [
                np.concatenate([mine, theirs]) if isinstance(mine, np.ndarray) else mine + theirs
                for mine, theirs in zip(columns, orbit_rows, strict=True)
            ]
    # by observation index, as the epoch lists them (already so, the usual case, when no row was merged)
    listed: list[int] = columns[0].tolist()
    if listed == sorted(listed):
        order = list(range(len(listed)))
        arrays: list[np.ndarray] = [columns[c] for c in _ARRAY_COLUMNS]
    else:
        take = np.argsort(columns[0], kind="stable")
        order = take.tolist()
        arrays = [columns[c][take] for c in _ARRAY_COLUMNS]
    prn, pseudorange, cn0, position, clock, carrier, range_rate, velocity, drift = arrays
    doppler = bool(np.isfinite(range_rate).any())
    prs = PseudorangeSet(
        gpst,
        tuple(columns[1][k] for k in order),
        prn,
        pseudorange,
        cn0,
        position,
        clock,
        carrier,
        range_rate if doppler else None,
        velocity if doppler else None,
        drift if doppler else None,
    )
    indices = [listed[k] for k in order]
    return EpochSatellites(prs, indices, doppler_reasons, [columns[11][k] for k in order])


_Columns = list[Any]
"""An epoch's satellite rows as columns: observation index (int), system (list), PRN (int), pseudorange, C/N0,
position (n, 3), clock (s), carrier (Hz), range rate, velocity (n, 3), clock drift, ephemeris issue (list)."""
_ARRAY_COLUMNS = (2, 3, 4, 5, 6, 7, 8, 9, 10)
"""The columns from the PRN to the clock drift, numpy arrays."""


def _client_rows(rows: list[tuple[Any, ...]]) -> _Columns:
    """The columns of the rows whose satellite state the client sent (tuples in the columns' order)."""
    count = len(rows)
    return [
        np.array([r[0] for r in rows], dtype=int),
        [r[1] for r in rows],
        np.array([r[2] for r in rows], dtype=int),
        np.array([r[3] for r in rows], dtype=float),
        np.array([r[4] for r in rows], dtype=float),
        np.array([r[5] for r in rows], dtype=float).reshape(count, 3),
        np.array([r[6] for r in rows], dtype=float),
        np.array([r[7] for r in rows], dtype=float),
        np.array([r[8] for r in rows], dtype=float),
        np.array([r[9] for r in rows], dtype=float).reshape(count, 3),
        np.array([r[10] for r in rows], dtype=float),
        [r[11] for r in rows],
    ]


def _orbit_rows(
    ephemerides: Ephemerides,
    observed: list[PseudorangeObservation],
    systems: list[str],
    need_orbit: list[int],
    ephemeris_index: np.ndarray,
    issues: list[Issue | None],
    have: np.ndarray,
    gpst: float,
    use_doppler: bool,
    no_group_delay: frozenset[str],
) -> _Columns:
    """The columns of the rows ``have`` (of ``observed``, those with an ephemeris): their satellites' states
    at transmit time from the broadcast orbits, in one vectorised evaluation; a position the client sent
    without its clock replaces the orbit's. The systems of ``no_group_delay`` get their clocks without the
    broadcast group delay (the session's ``galileo_group_delay``)."""
    factors = np.array(
        [_NO_DELAY if systems[r] in no_group_delay else _DELAY_FACTORS[systems[r]] for r in have]
    )
    picked = [observed[r] for r in have]
    pseudoranges = np.array([o.pseudorange for o in picked])
    states = transmit_states(ephemerides.orbits, ephemeris_index[have], gpst, pseudoranges, factors)
    frequencies = np.array([_FREQUENCY[o.system] for o in picked])
    # one vectorised conversion (element-wise, so each row's value is as if alone)
    rates = doppler_to_range_rate(
        np.array([o.doppler_hz if (o.doppler_hz is not None and use_doppler) else math.nan for o in picked]),
        frequencies,
    )
    position = np.array(states.position, dtype=float)
    for k, o in enumerate(picked):
        if o.sat_position is not None:
            position[k] = np.asarray(o.sat_position, float)
    return [
        np.array([need_orbit[r] for r in have.tolist()], dtype=int),
        [o.system for o in picked],
        np.array([o.prn for o in picked], dtype=int),
        pseudoranges.astype(float),
        np.array([o.cn0 for o in picked], dtype=float),
        position,
        np.array(states.clock_s, dtype=float),
        frequencies.astype(float),
        np.array(rates, dtype=float),
        np.array(states.velocity, dtype=float),
        np.array(states.clock_drift, dtype=float),
        [
            None if o.sat_position is not None else issues[r]
            for r, o in zip(have.tolist(), picked, strict=True)
        ],
    ]


CLIENT_STATE = "satellite position sent by the client: its ephemeris issue is unknown"


def apply_corrections(
    satellites: EpochSatellites,
    corrections: CorrectionTable,
    options: Mapping[str, Any],
    ionosphere: bool,
    reported: CorrectionUses,
) -> EpochSatellites:
    """Add each row's differential correction (same satellite, same ephemeris issue, newest base epoch at or
    before this one, within the correction source's maximum age); record per observation whether one was added or why
    not. The rover keeps its own atmosphere models: a correction holds their error at the base only."""
    prs = satellites.prs
    max_age = corrections.max_age_s
    delta = np.full(len(prs), np.nan)
    systems = options.get("correction_systems")  # None: a session stored before the option (all)
    for row, (sat, issue) in enumerate(zip(prs.sats, satellites.issues)):
        i = satellites.indices[row]
        if systems is not None and sat[0] not in systems:
            reported[i] = (False, SYSTEM_NOT_CORRECTED)
            continue
        if issue is None:
            reported[i] = (False, CLIENT_STATE)
            continue
        found = corrections.lookup(sat, issue, prs.gpst, max_age)
        if isinstance(found, str):
            reported[i] = (False, found)
            continue
        value = found.value_m
        if not ionosphere:
            value += found.ionosphere_m
        if not options["troposphere"]:
            value += found.troposphere_m
        delta[row] = value
        reported[i] = (True, None)
    corrected = np.isfinite(delta)
    pseudoranges = prs.pseudorange_m + np.where(corrected, delta, 0.0)
    return replaced(satellites, prs=replaced(prs, pseudorange_m=pseudoranges), corrected=corrected)


MIXED_MIN_CORRECTED = 2
"""A constellation's uncorrected rows are left out (``mixed_corrections`` exclude) only while at least this
many of its rows are corrected: two corrected rows still add geometry beyond their own clock, one would
only fix it."""


def leave_out_mixed(
    satellites: EpochSatellites, rows: np.ndarray, uses: dict[int, MeasurementUse]
) -> np.ndarray:
    """``rows`` without the uncorrected ones of a constellation with at least MIXED_MIN_CORRECTED corrected
    rows among ``rows``, each left out with its reason. A correction is relative to the base's per-
    constellation median model error (gnss/differential.py), so the corrected rows' clock carries that
    median and an uncorrected row of the same constellation sits its own model error minus the median
    away from it (2.0 m median for BeiDou C36 on tests/data/gnss-rover): a bias the filter's one clock per
    constellation cannot absorb. Its own clock would take its whole range, which for a lone satellite is
    leaving it out; so is this, without a filter state per constellation and correction state. ``rows``
    itself without corrections."""
    corrected = satellites.corrected
    if corrected is None or rows.size == 0 or corrected[rows].all():
        return rows
    systems = np.array(satellites.prs.systems)
    out = np.zeros(len(systems), dtype=bool)
    for system in set(systems[rows].tolist()):
        member = rows[systems[rows] == system]
        count = int(corrected[member].sum())
        if count < MIXED_MIN_CORRECTED:
            continue
        for row in member[~corrected[member]]:
            out[row] = True
            i = satellites.indices[row]
            uses[i] = MeasurementUse(
                i,
                "pseudorange",
                False,
                f"no differential correction while {count} {system} satellites have one: its range would sit "
                "its own broadcast-model error from their clock, which holds the base's median "
                "(options.mixed_corrections exclude)",
            )
    kept: np.ndarray = rows[~out[rows]]
    return kept


def without_mixed(satellites: EpochSatellites, uses: dict[int, MeasurementUse]) -> EpochSatellites:
    """The epoch without the rows :func:`leave_out_mixed` leaves out, judged over all its rows (the
    least-squares start, before any position for an elevation mask)."""
    everything = np.arange(len(satellites.prs))
    kept = leave_out_mixed(satellites, everything, uses)
    if kept.size == everything.size:
        return satellites
    keep = np.zeros(everything.size, dtype=bool)
    keep[kept] = True
    corrected = satellites.corrected
    return EpochSatellites(
        satellites.prs.subset(keep),
        [satellites.indices[r] for r in kept],
        satellites.doppler_reasons,
        [satellites.issues[r] for r in kept] if satellites.issues else [],
        None if corrected is None else corrected[kept],
    )


def atmosphere_of(options: Mapping[str, Any], ephemerides: Ephemerides | None) -> Atmosphere:
    klobuchar = (
        ephemerides.navigation.klobuchar_gps if (ephemerides is not None and options["ionosphere"]) else None
    )
    return Atmosphere(klobuchar, options["troposphere"])


def carrier_smoothed(
    session: GnssSession, t: float, satellites: EpochSatellites, observations: Sequence[Observation]
) -> tuple[EpochSatellites, np.ndarray, np.ndarray]:
    """Carrier-smoothed code (``carrier_smoothing`` hatch or hatch+tdcp): each row with carrier_cycles advances its
    satellite's Hatch filter and gets the smoothed pseudorange; returns the epoch with them and, per row, the
    factor on its noise std (1 for raw code) and the epochs averaged (0 for raw code). Runs before
    differential corrections, which change with the base's epoch and must not be averaged."""
    prs = satellites.prs
    factor = np.ones(len(prs))
    options = session.options
    if options.get("carrier_smoothing", "off") not in ("hatch", "hatch+tdcp") or not len(prs):
        return satellites, factor, np.zeros(len(prs))
    phases = epoch_phases(satellites, observations, options)
    carrier, doppler_hz, lli = phases
    if not np.isfinite(carrier).any():
        return satellites, factor, np.zeros(len(prs))
    settings = (
        options["hatch_window_s"],
        options["carrier_slip_cycles_per_s"],
        options["carrier_code_jump_m"],
        options["carrier_max_gap_s"],
    )
    wavelength = SPEED_OF_LIGHT / prs.frequency_hz
    if compiled_enabled():
        pseudoranges, count = _compiled_hatch(session, t, prs, phases, wavelength, settings)
    else:
        tracks = session.carrier.tracks()
        result = hatch_update(
            tracks,
            t,
            prs.sats,
            prs.pseudorange_m,
            carrier,
            wavelength,
            doppler_hz,
            lli,
            _hatch_config(*settings),
        )
        session.carrier = CarrierTable.from_tracks(tracks)
        pseudoranges, count = result.pseudorange_m, result.count
    smoothed = count >= 1.0
    factor[smoothed] = np.maximum(1.0 / np.sqrt(count[smoothed]), options["hatch_std_floor"])
    prs = replaced(prs, pseudorange_m=pseudoranges)
    return replaced(satellites, prs=prs, phases=phases), factor, count


@functools.lru_cache(maxsize=64)
def _hatch_config(
    window_s: float, slip_cycles_per_s: float, code_jump_m: float, max_gap_s: float
) -> HatchConfig:
    """The Hatch filter's settings from the session's options (built once per distinct set)."""
    return HatchConfig(window_s, slip_cycles_per_s, code_jump_m, max_gap_s)


def _compiled_hatch(
    session: GnssSession,
    t: float,
    prs: PseudorangeSet,
    phases: tuple[np.ndarray, np.ndarray, np.ndarray],
    wavelength: np.ndarray,
    settings: tuple[float, float, float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """``gnss.carrier.hatch_update`` by ``hatch_kernel`` on the session's track table (the same smoothed
    ranges and counts to the bit); returns them and leaves the new table in the session."""
    n = len(prs)
    old = session.carrier
    cycles, doppler_hz, lli = phases
    smoothed, count, reset = np.empty(n), np.empty(n), np.empty(n, dtype=np.int64)
    table, origin = np.empty((n + len(old), 6)), np.empty(n + len(old), dtype=np.int64)
    rows = hatch_kernel(
        t,
        prs.pseudorange_m,
        cycles,
        wavelength,
        doppler_hz,
        lli,
        old.rows(prs.sats),
        old.table,
        np.array(settings, dtype=float),
        smoothed,
        count,
        reset,
        table,
        origin,
    )
    sats, known = prs.sats, old.sats
    session.carrier = CarrierTable(
        [sats[k] if k >= 0 else known[-1 - k] for k in origin[:rows].tolist()], table[:rows]
    )
    return smoothed, count


def epoch_phases(
    satellites: EpochSatellites, observations: Sequence[Observation], options: dict[str, Any]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of the epoch's set: carrier phase (NaN: none), Doppler (NaN: none or unused) and LLI (0: not
    sent)."""
    # satellites.indices are the epoch's pseudoranges (satellite_states keeps no other kind)
    sent = [cast(PseudorangeObservation, observations[i]) for i in satellites.indices]
    use_doppler = bool(options.get("use_doppler", True))
    cycles = np.array([math.nan if o.carrier_cycles is None else o.carrier_cycles for o in sent], dtype=float)
    doppler = np.array(
        [o.doppler_hz if (o.doppler_hz is not None and use_doppler) else math.nan for o in sent], dtype=float
    )
    lli = np.array([o.lli or 0 for o in sent], dtype=int)
    return cycles, doppler, lli


_Frozen = TypeVar("_Frozen", PseudorangeSet, EpochSatellites)


def replaced(value: _Frozen, **changes: Any) -> _Frozen:
    """``dataclasses.replace`` of an epoch's satellites or pseudorange set without running ``__init__`` (a
    copy of the instance's dict with ``changes`` over it: a fifth of replace's cost), which also keeps the
    set's formatted satellite names (``sats``) when its systems and PRNs stay. Valid because neither class
    has a ``__post_init__`` or slots (tests/pipelines/test_pipeline_gnss_shared.py checks both and holds it
    to replace)."""
    if "systems" in changes or "prns" in changes:
        raise ValueError("replaced() keeps the satellite names: change only other fields")
    copy = object.__new__(type(value))
    fields = copy.__dict__
    fields.update(value.__dict__)
    fields.update(changes)
    return copy
