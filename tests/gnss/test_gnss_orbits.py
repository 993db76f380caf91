"""Broadcast orbits: real ephemerides checked by physics and by each other, and pseudoranges at the reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.gnss.geodesy import ecef_to_geodetic, geodetic_to_ecef
from edgepos.gnss.measurements import Atmosphere, prepare_epoch, without_group_delay
from edgepos.gnss.orbits import (
    GALILEO_E5A_CLOCK,
    OMEGA_EARTH,
    SPEED_OF_LIGHT,
    BroadcastOrbits,
    earth_rotation,
    group_delay_factors,
    sagnac_range,
)
from edgepos.gnss.rinex_nav import NavigationData
from edgepos.gnss.rinex_obs import ObservationEpoch

T0 = 2134 * 604800.0 + 45600.0  # 2020-11-29 12:40:00 GPST, the recording's first epoch


def _index(orbits: BroadcastOrbits, sat: str, toe_hour: float) -> int:
    for i, e in enumerate(orbits.ephemerides):
        if e.sat == sat and abs((e.toe % 86400.0) / 3600.0 - toe_hour) < 0.01:
            return i
    raise LookupError(sat)


def _at(orbits: BroadcastOrbits, index: int, t: float) -> np.ndarray:
    position, _ = orbits.position(np.array([index]), np.array([t]))
    return position[0]


@pytest.mark.parametrize(
    ("sat", "hour_a", "hour_b"),
    [
        ("G05", 12.0, 14.0),
        ("G02", 12.0, 14.0),
        ("C21", 11.004, 12.004),
        ("C10", 11.004, 12.004),
        ("C05", 11.004, 12.004),
        ("E07", 12.0, 12.5),
    ],
)
def test_consecutive_ephemerides_agree(
    orbits: BroadcastOrbits, sat: str, hour_a: float, hour_b: float
) -> None:
    """Two independent uploads evaluated at the same instant (one forwards, one backwards from its toe) give
    the same point to metres; a wrong sign or frame in the formulas would separate them by kilometres."""
    a = _at(orbits, _index(orbits, sat, hour_a), T0)
    b = _at(orbits, _index(orbits, sat, hour_b), T0)
    assert np.linalg.norm(a - b) < 3.0


def test_orbit_radii_and_geostationary_slot(orbits: BroadcastOrbits, nav: NavigationData) -> None:
    for sat, hour, low, high in [
        ("G05", 12.0, 26.0e6, 26.9e6),
        ("C21", 12.004, 27.7e6, 28.1e6),
        ("C10", 12.004, 42.0e6, 42.6e6),
        ("E07", 12.0, 29.4e6, 29.8e6),
    ]:
        index = _index(orbits, sat, hour)
        eph = orbits.ephemerides[index]
        radius = float(np.linalg.norm(_at(orbits, index, T0)))
        a = eph.sqrt_a**2
        assert a * (1 - eph.e) - 2e3 < radius < a * (1 + eph.e) + 2e3
        assert low < radius < high
    # C05 is BeiDou's GEO at 58.75 deg E: near the equator, near its slot, and almost fixed in ECEF.
    geo = _index(orbits, "C05", 12.004)
    position = _at(orbits, geo, T0)
    lat, lon, _height = ecef_to_geodetic(position)
    assert abs(math.degrees(float(lat))) < 3.0
    assert math.degrees(float(lon)) == pytest.approx(58.75, abs=0.5)
    assert float(np.linalg.norm(position)) == pytest.approx(42164e3, abs=100e3)
    drift = np.linalg.norm(_at(orbits, geo, T0 + 60.0) - position) / 60.0
    # m/s in ECEF: a 1.7 deg inclination gives a daily north-south swing of up to ~90 m/s; the MEO formula
    # applied to a GEO would give ~3 km/s.
    assert drift < 100.0
    # The IGSO C10 moves ~1-3 km/s in ECEF, not tens.
    igso = _index(orbits, "C10", 12.004)
    speed = np.linalg.norm(_at(orbits, igso, T0 + 1.0) - _at(orbits, igso, T0))
    assert 300.0 < speed < 4000.0


def test_ephemeris_selection(orbits: BroadcastOrbits) -> None:
    index = orbits.select(["G", "G", "C", "C", "G", "C"], [5, 28, 7, 5, 14, 99], T0)
    chosen = [orbits.ephemerides[i] if i >= 0 else None for i in index]
    assert (chosen[0].toe % 86400) == 43200.0  # 12:00 nearer than 14:00
    assert (chosen[1].toe % 86400) == 50400.0  # only 14:00 exists, within half the 4 h fit interval
    assert chosen[2].sat == "C07"  # only the 11:00 BDT upload, 1 h 40 min old
    assert (chosen[3].toe % 86400) == pytest.approx(43214.0)  # 12:00 BDT = 12:00:14 GPST
    assert chosen[4] is None  # G14 is flagged unhealthy
    assert chosen[5] is None
    assert orbits.select(["G"], [5], T0 + 3 * 3600.0)[0] >= 0
    assert orbits.select(["G"], [5], T0 + 6 * 3600.0)[0] == -1


def test_sagnac_rotation_and_closed_form_agree() -> None:
    satellite = np.array([[15.1e6, -7.9e6, 20.2e6], [21.9e6, 36.0e6, -1.2e6]])
    receiver = geodetic_to_ecef(math.radians(41.64), math.radians(2.35), 250.0)
    tau = np.linalg.norm(satellite - receiver, axis=1) / SPEED_OF_LIGHT
    for _ in range(3):
        rotated = earth_rotation(satellite, tau)
        tau = np.linalg.norm(rotated - receiver, axis=1) / SPEED_OF_LIGHT
    exact = np.linalg.norm(earth_rotation(satellite, tau) - receiver, axis=1)
    assert sagnac_range(satellite, receiver) == pytest.approx(exact, abs=2e-3)
    # The correction itself is tens of metres at most for a ground receiver.
    assert np.all(np.abs(exact - np.linalg.norm(satellite - receiver, axis=1)) < 50.0)
    assert OMEGA_EARTH * 0.07 * 26e6 > 100.0  # the rotation moves a GPS satellite ~130 m during travel


def test_pseudoranges_consistent_at_reference(
    orbits: BroadcastOrbits, nav: NavigationData, epochs: list[ObservationEpoch]
) -> None:
    """At the reference position, measured minus modelled pseudoranges (clock, TGD, relativity, Klobuchar,
    Saastamoinen, Sagnac) equal one receiver clock per constellation plus metres of noise and multipath."""
    epoch = epochs[18]  # 12:40:18, the first epoch with the GEO C05's B1I pseudorange
    assert "C05" in epoch.sats
    prs, dropped = prepare_epoch(epoch, orbits, {"G": ("C1C", "S1C"), "C": ("C2I", "S2I")})
    assert all(sat[0] == "E" for sat in dropped)  # every GPS and BeiDou satellite has a valid ephemeris
    receiver = geodetic_to_ecef(math.radians(41.6425591030), math.radians(2.3540489690), 251.7823)
    iono, tropo, elevation, _ = Atmosphere.from_navigation(nav).delays(receiver, prs)
    residual = prs.pseudorange_m + SPEED_OF_LIGHT * prs.sat_clock_s - sagnac_range(prs.sat_position, receiver)
    residual -= iono + tropo
    systems = np.array(prs.systems)
    for system in "GC":
        rows = (systems == system) & (elevation > math.radians(10.0))
        centred = residual[rows] - np.median(residual[rows])
        assert np.all(np.abs(centred) < 15.0), (system, dict(zip(np.array(prs.sats)[rows], centred.round(1))))
    geo_row = prs.sats.index("C05")
    assert abs(residual[geo_row] - np.median(residual[systems == "C"])) < 15.0
    # Without the corrections the same check fails by tens of metres (the test can tell right from wrong).
    raw = prs.pseudorange_m - np.linalg.norm(prs.sat_position - receiver, axis=1)
    assert np.ptp(raw[systems == "G"]) > 1000.0


@pytest.mark.parametrize(
    ("sat", "hour"), [("G05", 12.0), ("C21", 12.004), ("C10", 12.004), ("C05", 12.004), ("E07", 12.0)]
)
def test_velocity_and_clock_drift(orbits: BroadcastOrbits, sat: str, hour: float) -> None:
    """Velocity and clock drift against a wider finite difference of the position and clock, and the speed
    against vis-viva once the Earth's rotation is added back (an error of scale, step or frame breaks one)."""
    index = _index(orbits, sat, hour)
    i = np.array([index])
    velocity, drift = orbits.rates(i, np.array([T0]))
    wide = (_at(orbits, index, T0 + 2.0) - _at(orbits, index, T0 - 2.0)) / 4.0
    # Truncation of the 2 s difference: (2 s)^2 / 6 * 8e-5 m/s^3 = 5e-5 m/s.
    assert np.linalg.norm(velocity[0] - wide) < 2e-4
    clock = [
        orbits.clock_polynomial(i, np.array([t]))[0] + orbits.position(i, np.array([t]))[1][0]
        for t in (T0 - 2.0, T0 + 2.0)
    ]
    assert drift[0] == pytest.approx((clock[1] - clock[0]) / 4.0, abs=1e-15)
    position = _at(orbits, index, T0)
    eph = orbits.ephemerides[index]
    if sat != "C05":  # the GEO's ECEF position is rotated by the ICD's own rule; vis-viva holds in any case
        inertial = velocity[0] + np.cross([0.0, 0.0, OMEGA_EARTH], position)
        gm = 3.986004418e14
        expected = math.sqrt(gm * (2.0 / np.linalg.norm(position) - 1.0 / eph.sqrt_a**2))
        assert np.linalg.norm(inertial) == pytest.approx(expected, rel=2e-4)
    else:
        assert np.linalg.norm(velocity[0]) < 100.0


def test_transmit_states_carry_rates(orbits: BroadcastOrbits) -> None:
    """transmit_states evaluates the transmit time and the rates' two points in one stacked call: every
    satellite valid at T0 (GPS, BeiDou GEO/IGSO/MEO, Galileo) gets what position and rates give alone."""
    sats = sorted({(e.system, e.prn) for e in orbits.ephemerides})
    index = orbits.select([s for s, _ in sats], [p for _, p in sats], T0)
    index = index[index >= 0]
    assert len(index) > 20 and orbits._geo[index].any()
    pseudoranges = np.linspace(2.0e7, 3.9e7, len(index))
    factors = np.tile([[1.0, 0.0]], (len(index), 1))
    states = orbits.transmit_states(index, T0, pseudoranges, factors)
    velocity, drift = orbits.rates(index, states.t_transmit)
    assert np.allclose(states.velocity, velocity, rtol=0.0, atol=1e-9)
    assert np.allclose(states.clock_drift, drift, rtol=0.0, atol=1e-18)
    for k, i in enumerate(index):  # each satellite as if alone
        position, relativistic = orbits.position(np.array([i]), states.t_transmit[k : k + 1])
        clock = orbits.clock_polynomial(np.array([i]), states.t_transmit[k : k + 1]) + relativistic
        clock -= orbits.group_delay(np.array([i]), factors[k : k + 1])
        assert np.allclose(states.position[k], position[0], rtol=0.0, atol=1e-6)
        assert states.clock_s[k] == pytest.approx(clock[0], abs=1e-15)


def test_selection_matches_a_plain_search(orbits: BroadcastOrbits) -> None:
    """select against the rule written out: the valid record with the nearest toe, the later one on a tie."""
    sats = sorted({(e.system, e.prn) for e in orbits.ephemerides}) + [("G", 99)]
    toe = np.array([e.toe for e in orbits.ephemerides])
    for hours in np.arange(-6.0, 8.0, 0.25):
        t = T0 + 3600.0 * hours
        chosen = orbits.select([s for s, _ in sats], [p for _, p in sats], t)
        for (system, prn), index in zip(sats, chosen):
            valid = [
                i
                for i, e in enumerate(orbits.ephemerides)
                if (e.system, e.prn) == (system, prn) and abs(t - toe[i]) <= orbits._max_age[i]
            ]
            expected = min(valid, key=lambda i: (abs(t - toe[i]), -i)) if valid else -1
            assert index == expected, (system, prn, hours)


def test_dopplers_consistent_at_reference(orbits: BroadcastOrbits, epochs: list[ObservationEpoch]) -> None:
    """At the reference position and velocity (central difference of the reference), -lambda D minus the
    modelled range rate (satellite velocity and clock drift, Sagnac rate) is one receiver clock drift for all
    satellites plus noise: measured robust std 0.15 m/s over the first half. A wrong Doppler sign, wavelength
    or frame would leave hundreds of m/s."""
    from edgepos.gnss.orbits import sagnac_range_rate
    from edgepos.gnss.spp import read_reference, reference_velocity
    from gnsshelp import REFERENCE

    ref_time, ref_ecef = read_reference(str(REFERENCE))
    ref_velocity = reference_velocity(ref_time, ref_ecef)
    centred = []
    for epoch in epochs[10:40]:
        j = int(np.argmin(np.abs(ref_time - epoch.gpst)))
        assert abs(ref_time[j] - epoch.gpst) < 0.05 and np.all(np.isfinite(ref_velocity[j]))
        prs, _ = prepare_epoch(epoch, orbits, {"G": ("C1C", "S1C"), "C": ("C2I", "S2I")})
        assert (
            prs.range_rate_mps is not None
            and prs.sat_velocity is not None
            and prs.sat_clock_drift is not None
        )
        modelled = sagnac_range_rate(prs.sat_position, prs.sat_velocity, ref_ecef[j], ref_velocity[j])
        residual = prs.range_rate_mps - modelled + SPEED_OF_LIGHT * prs.sat_clock_drift
        centred.extend(residual - np.median(residual))
    spread = 1.4826 * float(np.median(np.abs(centred)))
    assert spread < 0.4
    assert np.mean(np.abs(centred) < 3.0) > 0.95


def test_remembered_selection_is_the_search_at_every_time(orbits: BroadcastOrbits) -> None:
    """``select`` reuses a satellite's last choice between the points where it may change (validity edges,
    toe midpoints): at times right at, just inside and just outside every such point, visited forwards and
    backwards on one object and on a fresh one each time, it answers what the plain rule does."""
    records = {(e.system, e.prn) for e in orbits.ephemerides}
    sats = sorted(records)[::5] + [("G", 99)]
    toe = np.array([e.toe for e in orbits.ephemerides])
    points = set()
    for system, prn in sats:
        mine = [i for i, e in enumerate(orbits.ephemerides) if (e.system, e.prn) == (system, prn)]
        points |= {float(toe[i] + sign * orbits._max_age[i]) for i in mine for sign in (-1.0, 1.0)}
        points |= {0.5 * float(toe[i] + toe[j]) for i in mine for j in mine if toe[i] != toe[j]}
    times = sorted(p + d for p in points for d in (-2e-3, -5e-4, 0.0, 5e-4, 2e-3, 0.7, 30.0))
    assert len(times) > 200
    kept = BroadcastOrbits(orbits.ephemerides)
    for t in times + times[::-1]:
        remembered = kept.select([s for s, _ in sats], [p for _, p in sats], t)
        fresh = BroadcastOrbits(orbits.ephemerides).select([s for s, _ in sats], [p for _, p in sats], t)
        for (system, prn), index, again in zip(sats, remembered, fresh, strict=True):
            valid = [
                i
                for i, e in enumerate(orbits.ephemerides)
                if (e.system, e.prn) == (system, prn) and abs(t - toe[i]) <= orbits._max_age[i]
            ]
            expected = min(valid, key=lambda i: (abs(t - toe[i]), -i)) if valid else -1
            assert index == again == expected, (system, prn, t)


def test_the_ephemerides_week_is_numpys_rounding(nav: NavigationData) -> None:
    """``Ephemerides.gpst`` rounds the week with Python's ``round`` (half to even), as ``np.round`` did: the
    same continuous second for times of week all over the week and at the exact half-week ties."""
    from edgepos.gnss.ephemerides import Ephemerides
    from edgepos.gnss.timesys import SECONDS_PER_WEEK

    ephemerides = Ephemerides.from_navigation(nav)
    window = ephemerides.validity()
    assert window is not None
    middle = 0.5 * (window[0] + window[1])
    k = math.floor(middle / SECONDS_PER_WEEK - 0.5)
    tie = middle - (k + 0.5) * SECONDS_PER_WEEK  # a time of week half a week from the middle
    assert 0.0 <= tie < SECONDS_PER_WEEK and (middle - tie) / SECONDS_PER_WEEK == k + 0.5
    times = [tie, math.nextafter(tie, 0.0), math.nextafter(tie, 1e9)]
    times += np.linspace(0.0, SECONDS_PER_WEEK, 997).tolist()
    for t in times:
        week = np.round((middle - t) / SECONDS_PER_WEEK)
        assert ephemerides.gpst(t) == float(week * SECONDS_PER_WEEK + t)


def _galileo_e1_clocks(orbits: BroadcastOrbits, sat: str, t: float) -> dict[int, float]:
    """Per record of ``sat`` (index), its E1 clock at ``t`` (m): the clock polynomial less the group delay
    the factors of a C1C pseudorange take from it."""
    factors = np.array([group_delay_factors("E", "C1C")])
    clocks = {}
    for index, e in enumerate(orbits.ephemerides):
        if e.sat == sat and abs(t - e.toe) <= 4 * 3600.0:
            rows = np.array([index])
            clock = orbits.clock_polynomial(rows, np.array([t])) - orbits.group_delay(rows, factors)
            clocks[index] = float(clock[0]) * SPEED_OF_LIGHT
    return clocks


@pytest.mark.parametrize("sat", ["E12", "E07", "E21", "E33"])
def test_galileo_inav_and_fnav_records_give_one_e1_clock(orbits: BroadcastOrbits, sat: str) -> None:
    """An I/NAV record's clock is the E1/E5b pair's, an F/NAV record's the E1/E5a pair's; each less its own
    pair's BGD is the E1 clock (Galileo OS SIS ICD 5.1.5), the same to decimetres. Taking BGD(E1, E5b) from
    an F/NAV record, which does not broadcast it (blank: 0), put them |BGD(E1, E5a)| apart: 3.1 m for E12."""
    clocks = _galileo_e1_clocks(orbits, sat, T0)
    sources = {orbits.ephemerides[i].data_sources & GALILEO_E5A_CLOCK for i in clocks}
    assert sources == {0, GALILEO_E5A_CLOCK}  # both kinds of record in the file
    assert max(clocks.values()) - min(clocks.values()) < 0.3
    if sat == "E12":
        fnav = next(i for i in clocks if orbits.ephemerides[i].data_sources & GALILEO_E5A_CLOCK)
        assert abs(orbits.ephemerides[fnav].tgd2 * SPEED_OF_LIGHT) > 3.0  # the delay that was left out


def test_an_e5b_code_needs_an_inav_record(orbits: BroadcastOrbits) -> None:
    """BGD(E1, E5b) comes only with I/NAV records: an E5b pseudorange is not given an F/NAV record's clock."""
    fnav = next(
        i for i, e in enumerate(orbits.ephemerides) if e.system == "E" and e.data_sources & GALILEO_E5A_CLOCK
    )
    inav = next(
        i
        for i, e in enumerate(orbits.ephemerides)
        if e.system == "E" and not e.data_sources & GALILEO_E5A_CLOCK
    )
    assert not orbits.signal_usable(fnav, "E", "C7Q")
    assert orbits.signal_usable(inav, "E", "C7Q")
    assert orbits.signal_usable(fnav, "E", "C1C") and orbits.signal_usable(fnav, "E", "C5Q")
    assert orbits.signal_usable(fnav, "G", "C1C")


def test_a_receiver_without_the_galileo_group_delay_moves_galileo_clocks_only(
    orbits: BroadcastOrbits, epochs: list[ObservationEpoch]
) -> None:
    """``galileo_group_delay`` none gives each Galileo satellite its clock without the record's BGD, by exactly
    that BGD, and leaves GPS and BeiDou as they are."""
    epoch = epochs[30]
    broadcast, _ = prepare_epoch(epoch, orbits)
    none, _ = prepare_epoch(epoch, orbits, no_group_delay=without_group_delay("none"))
    assert broadcast.sats == none.sats and "E12" in broadcast.sats
    chosen = orbits.select(broadcast.systems, broadcast.prns, epoch.gpst)
    factors = np.array([group_delay_factors(s, "C1C" if s != "C" else "C2I") for s in broadcast.systems])
    delay = orbits.group_delay(chosen, factors)
    galileo = np.array(broadcast.systems) == "E"
    shift = none.sat_clock_s - broadcast.sat_clock_s
    assert np.allclose(shift[galileo], delay[galileo], rtol=0.0, atol=1e-15)
    assert np.all(shift[~galileo] == 0.0)
    assert np.any(np.abs(delay[galileo]) * SPEED_OF_LIGHT > 1.0)
    with pytest.raises(ValueError, match="galileo group delay"):
        without_group_delay("ICD")
