"""The simulated Doppler (sim.gnss_doppler): the satellites' Earth-fixed velocities are their positions' rates;
a reflected path's rate is taken within a place only; the noise follows the recording's figures by C/N0; a
run's Dopplers agree with its carrier phases' changes; and adding them changes no other number of a run."""

from __future__ import annotations

import dataclasses
from collections import defaultdict

import numpy as np
import pytest
from edgepos.core.observations import PseudorangeObservation
from edgepos.gnss.orbits import SPEED_OF_LIGHT
from edgepos.sim.constellation import gps_bds_constellation
from edgepos.sim.gnss_doppler import DOPPLER_CN0_DBHZ, DOPPLER_STD_MPS, noise_std, path_rate
from edgepos.sim.gnss_scenario import urban_scenario
from edgepos.sim.gnss_sensors import FREQUENCY_HZ, simulate


def test_the_satellite_velocity_is_the_rate_of_its_earth_fixed_position() -> None:
    constellation = gps_bds_constellation()
    t = 1.0e5 + np.linspace(
        0.0, 4.0e4, len(constellation)
    )  # each satellite its own time, as transmit times are
    h = 1.0e-3
    numeric = (constellation.ecef_each(t + h) - constellation.ecef_each(t - h)) / (2.0 * h)
    analytic = constellation.ecef_velocity_each(t)
    assert np.abs(analytic - numeric).max() < 1e-3
    speed = np.linalg.norm(analytic, axis=-1)
    geo = np.array([kind == "GEO" for kind in constellation.kinds])
    assert np.all(speed[geo] < 1.0) and np.all((speed[~geo] > 1.0e3) & (speed[~geo] < 4.0e3))


def test_a_path_rate_is_taken_within_a_place_only() -> None:
    step = 0.5
    path = np.array([0.0, 1.0, 2.0, 50.0, 53.0, 56.0, 80.0])[:, None] * np.array([[1.0, -2.0]])
    place = np.array([0, 0, 0, 1, 1, 1, 2])
    rate = path_rate(path, place, step)
    expected = np.array([2.0, 2.0, 2.0, 6.0, 6.0, 6.0, 0.0])[:, None] * np.array([[1.0, -2.0]])
    np.testing.assert_allclose(rate, expected)
    assert not path_rate(path[:1], place[:1], step).any()


def test_the_noise_follows_the_recordings_figures_by_cn0() -> None:
    np.testing.assert_allclose(noise_std(DOPPLER_CN0_DBHZ), DOPPLER_STD_MPS, rtol=1e-12)
    grid = np.linspace(20.0, 60.0, 81)
    std = noise_std(grid)
    assert np.all(np.diff(std) <= 0.0)
    assert std[0] == pytest.approx(DOPPLER_STD_MPS[0]) and std[-1] == pytest.approx(DOPPLER_STD_MPS[-1])


def _series(observations: list) -> dict[tuple[str, int], dict[float, PseudorangeObservation]]:
    by_satellite: dict[tuple[str, int], dict[float, PseudorangeObservation]] = defaultdict(dict)
    for o in observations:
        if isinstance(o, PseudorangeObservation):
            by_satellite[(o.system, o.prn)][o.t] = o
    return by_satellite


def test_the_doppler_agrees_with_the_carrier_phases_change() -> None:
    """Between two epochs 1 s apart in one lock, the phase's change (m) is the mean range rate over the
    second: the mean of the two Dopplers' rates within their noise (and the odd unflagged slip), once the
    receiver clock's white frequency noise, common to every satellite of the second and not in the
    Dopplers, is taken out as the second's median."""
    run = simulate(urban_scenario(short=True), np.random.default_rng([1, 0]))
    by_second: dict[float, list[tuple[float, float]]] = defaultdict(list)
    for (system, _), by_time in _series(run.observations).items():
        wavelength = SPEED_OF_LIGHT / FREQUENCY_HZ[system]
        for t, first in by_time.items():
            second = by_time.get(t + 1.0)
            if second is None or first.carrier_cycles is None or second.carrier_cycles is None or second.lli:
                continue
            assert first.doppler_hz is not None and second.doppler_hz is not None
            change = (second.carrier_cycles - first.carrier_cycles) * wavelength
            rate = -0.5 * (first.doppler_hz + second.doppler_hz) * wavelength
            std = 0.5 * float(np.hypot(noise_std(np.array(first.cn0)), noise_std(np.array(second.cn0))))
            by_second[t].append((change - rate, std))
    differences, normalised = [], []
    for pairs in by_second.values():
        if len(pairs) < 4:
            continue
        values = np.array(pairs)
        centred = values[:, 0] - np.median(values[:, 0])
        differences.extend(centred)
        normalised.extend(centred / values[:, 1])
    assert len(differences) > 300
    assert np.median(np.abs(differences)) < 0.1
    # a Gaussian's median |z| is 0.674; the median taken out, reflected paths and slips move it a little
    assert 0.4 < np.median(np.abs(normalised)) < 1.0


def test_the_doppler_changes_no_other_number_of_a_run() -> None:
    scenario = urban_scenario(short=True)
    with_doppler = simulate(scenario, np.random.default_rng([2, 0])).observations
    without = simulate(
        dataclasses.replace(scenario, doppler=None), np.random.default_rng([2, 0])
    ).observations
    codes = [o for o in with_doppler if isinstance(o, PseudorangeObservation)]
    assert all(o.doppler_hz is not None and o.sat_velocity is not None for o in codes)
    plain = [dataclasses.replace(o, doppler_hz=None, sat_velocity=None, sat_clock_drift=None) for o in codes]
    assert plain == [o for o in without if isinstance(o, PseudorangeObservation)]
    assert [o for o in with_doppler if not isinstance(o, PseudorangeObservation)] == [
        o for o in without if not isinstance(o, PseudorangeObservation)
    ]
