"""gnss_tight's compiled satellite geometry (core/measurements/gnss_geometry.py) against the numpy orbits and
atmosphere it replaces in the epoch (gnss/orbits.py ``transmit_states``, gnss/measurements.py
``Atmosphere.delays``), on every record of the recording's navigation file, and the switch back to numpy
with EDGEPOS_NUMBA=0."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from edgepos.core import compiled
from edgepos.core.measurements import gnss_geometry
from edgepos.gnss.geodesy import geodetic_to_ecef
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet
from edgepos.gnss.orbits import BroadcastOrbits, group_delay_factors
from edgepos.gnss.rinex_nav import read_navigation

DATA = Path(__file__).resolve().parents[1] / "data" / "gnss-rover"
CODES = {"G": "C1C", "C": "C2I", "E": "C1C"}

pytestmark = pytest.mark.skipif(
    not compiled.compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)"
)


@pytest.fixture(scope="module")
def navigation():  # type: ignore[no-untyped-def]
    return read_navigation(str(DATA / "broadcast-nav.rnx"))


def _every_record(orbits: BroadcastOrbits, offset: float) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Every record of the file at ``offset`` s from its toe, with a pseudorange of 20,000-26,000 km."""
    records = np.arange(len(orbits))
    toe = np.array([e.toe for e in orbits.ephemerides])
    rng = np.random.default_rng(int(abs(offset)) + 7)
    pseudoranges = rng.uniform(2.0e7, 2.6e7, len(records))
    factors = np.array([group_delay_factors(e.system, CODES[e.system]) for e in orbits.ephemerides])
    # one receive time per call: each record is evaluated at its own toe + offset through the pseudorange
    t_receive = float(np.median(toe) + offset)
    return records, t_receive, pseudoranges, factors


@pytest.mark.parametrize("offset", [-3500.0, -600.0, 0.0, 900.0, 3500.0])
def test_transmit_states_match_the_numpy_orbits(navigation, offset: float) -> None:  # type: ignore[no-untyped-def]
    """Positions to 1e-6 m and velocities to 1e-7 m/s (the two differ by a few units in the last place of
    the trigonometric functions: C library against numpy's SIMD ones), clocks and transmit times to 1e-18 s
    and 1e-9 s; GPS, BeiDou (its GEO satellites' rotation included) and Galileo."""
    orbits = BroadcastOrbits(navigation.ephemerides)
    assert {e.system for e in orbits.ephemerides} >= {"G", "C", "E"}
    assert any(e.system == "C" and e.prn <= 5 for e in orbits.ephemerides)  # a BeiDou GEO is in the file
    records, t_receive, pseudoranges, factors = _every_record(orbits, offset)
    reference = orbits.transmit_states(records, t_receive, pseudoranges, factors)
    kernel = gnss_geometry.transmit_states(orbits, records, t_receive, pseudoranges, factors)
    np.testing.assert_allclose(kernel.position, reference.position, rtol=0.0, atol=1e-6)
    np.testing.assert_allclose(kernel.velocity, reference.velocity, rtol=0.0, atol=1e-7)
    np.testing.assert_allclose(kernel.clock_s, reference.clock_s, rtol=0.0, atol=1e-18)
    np.testing.assert_allclose(kernel.clock_drift, reference.clock_drift, rtol=0.0, atol=1e-18)
    np.testing.assert_allclose(kernel.t_transmit, reference.t_transmit, rtol=0.0, atol=1e-9)
    np.testing.assert_array_equal(kernel.ephemeris_index, reference.ephemeris_index)
    # a satellite's state does not depend on the others in the call (one record alone gives the same)
    alone = gnss_geometry.transmit_states(orbits, records[3:4], t_receive, pseudoranges[3:4], factors[3:4])
    np.testing.assert_allclose(alone.position[0], kernel.position[3], rtol=0.0, atol=1e-6)


def _satellites(orbits: BroadcastOrbits, receiver: np.ndarray) -> PseudorangeSet:
    records, t_receive, pseudoranges, factors = _every_record(orbits, 300.0)
    states = orbits.transmit_states(records, t_receive, pseudoranges, factors)
    frequency = np.array([1561.098e6 if e.system == "C" else 1575.42e6 for e in orbits.ephemerides])
    systems = tuple(e.system for e in orbits.ephemerides)
    prns = np.array([e.prn for e in orbits.ephemerides])
    count = len(records)
    return PseudorangeSet(
        t_receive,
        systems,
        prns,
        pseudoranges,
        np.full(count, 40.0),
        states.position,
        states.clock_s,
        frequency,
    )


@pytest.mark.parametrize(
    "lat_deg, lon_deg, height",
    [(41.4, 2.1, 80.0), (-33.9, 151.2, -50.0), (0.0, -179.9, 3000.0), (89.9, 45.0, 10.0), (41.4, 2.1, 2.0e5)],
)
@pytest.mark.parametrize("klobuchar", [True, False])
@pytest.mark.parametrize("troposphere", [True, False])
def test_delays_match_the_numpy_atmosphere(  # type: ignore[no-untyped-def]
    navigation, lat_deg: float, lon_deg: float, height: float, klobuchar: bool, troposphere: bool
) -> None:
    """Ionosphere and troposphere to 1e-8 m, elevation and azimuth to 1e-12 rad, for every satellite of
    the file (most of them below the horizon, where the troposphere's 5-degree floor and the Klobuchar
    night term apply), receivers near the pole, the antimeridian, below the ellipsoid and above the
    troposphere (no delay there)."""
    orbits = BroadcastOrbits(navigation.ephemerides)
    receiver = geodetic_to_ecef(np.radians(lat_deg), np.radians(lon_deg), height)
    prs = _satellites(orbits, receiver)
    atmosphere = Atmosphere(navigation.klobuchar_gps if klobuchar else None, troposphere)
    assert not klobuchar or atmosphere.klobuchar is not None
    reference = atmosphere.delays(receiver, prs)
    kernel = gnss_geometry.delays(atmosphere, receiver, prs)
    for name, got, want, tolerance in zip(
        ("ionosphere", "troposphere", "elevation", "azimuth"), kernel, reference, (1e-8, 1e-8, 1e-12, 1e-12)
    ):
        np.testing.assert_allclose(got, want, rtol=0.0, atol=tolerance, err_msg=name)
    assert np.any(kernel[2] > 0.0) and np.any(kernel[2] < 0.0)


def test_numba_off_runs_the_numpy_reference(navigation, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """With EDGEPOS_NUMBA=0 the epoch's geometry is the numpy forms' exactly."""
    orbits = BroadcastOrbits(navigation.ephemerides)
    records, t_receive, pseudoranges, factors = _every_record(orbits, 0.0)
    receiver = geodetic_to_ecef(np.radians(41.4), np.radians(2.1), 80.0)
    atmosphere = Atmosphere(navigation.klobuchar_gps)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    states = gnss_geometry.transmit_states(orbits, records, t_receive, pseudoranges, factors)
    reference = orbits.transmit_states(records, t_receive, pseudoranges, factors)
    np.testing.assert_array_equal(states.position, reference.position)
    prs = _satellites(orbits, receiver)
    for got, want in zip(gnss_geometry.delays(atmosphere, receiver, prs), atmosphere.delays(receiver, prs)):
        np.testing.assert_array_equal(got, want)
