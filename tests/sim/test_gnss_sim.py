"""The GNSS + RISS simulation: constellation geometry, street-canyon mask, pseudorange model, RISS
sensor statistics, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.observations import PseudorangeObservation, RissObservation
from edgepos.gnss.corrections import saastamoinen_delay
from edgepos.gnss.geodesy import ecef_to_enu, ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT, sagnac_range
from edgepos.gnss.spp import solve_epoch
from edgepos.sim.constellation import (
    BDS_GEO_LONGITUDES_DEG,
    BDS_MEO_RADIUS_M,
    GEOSYNCHRONOUS_RADIUS_M,
    GPS_RADIUS_M,
    gps_bds_constellation,
)
from edgepos.sim.gnss_scenario import open_sky_scenario, urban_scenario
from edgepos.sim.gnss_sensors import simulate
from edgepos.sim.trajectory import Cruise, build_trajectory
from edgepos.sim.urban import ANTENNA_HEIGHT_M, StreetView, Turn

SIDEREAL_DAY = 2.0 * math.pi / OMEGA_EARTH


@pytest.fixture(scope="module")
def constellation():
    return gps_bds_constellation()


@pytest.fixture(scope="module")
def urban():
    return urban_scenario(short=True)


@pytest.fixture(scope="module")
def open_sky():
    return open_sky_scenario(short=True)


def test_orbit_radii_and_inclinations(constellation) -> None:
    positions = constellation.ecef(np.linspace(0.0, 86400.0, 97))
    radius = np.linalg.norm(positions, axis=-1)
    kinds = np.array(constellation.kinds)
    systems = np.array(constellation.systems)
    np.testing.assert_allclose(radius[:, systems == "G"], GPS_RADIUS_M, rtol=1e-12)
    np.testing.assert_allclose(radius[:, (systems == "C") & (kinds == "MEO")], BDS_MEO_RADIUS_M, rtol=1e-12)
    np.testing.assert_allclose(radius[:, kinds != "MEO"], GEOSYNCHRONOUS_RADIUS_M, rtol=1e-12)
    assert abs(GEOSYNCHRONOUS_RADIUS_M - 42_164e3) < 1e3
    # Highest latitude reached = inclination (55 deg) for inclined orbits.
    latitude = np.degrees(np.arcsin(positions[..., 2] / radius))
    inclined = kinds != "GEO"
    assert np.all(np.abs(latitude[:, inclined]).max(axis=0) > 54.0)
    assert np.all(np.abs(latitude[:, inclined]) <= 55.0 + 1e-9)
    # Orbital period of GPS: half a sidereal day within 5 s (a = 26 560 km is the rounded radius).
    gps_period = 2.0 * math.pi / constellation.mean_motion[systems == "G"][0]
    assert abs(gps_period - SIDEREAL_DAY / 2.0) < 5.0


def test_geo_stays_over_its_longitude_and_igso_repeats(constellation) -> None:
    t = np.linspace(0.0, 2.0 * 86400.0, 49) + 1.2e9
    positions = constellation.ecef(t)
    for prn, longitude in BDS_GEO_LONGITUDES_DEG.items():
        j = next(
            i
            for i, (s, p) in enumerate(zip(constellation.systems, constellation.prns))
            if s == "C" and p == prn
        )
        lon = np.degrees(np.arctan2(positions[:, j, 1], positions[:, j, 0])) % 360.0
        np.testing.assert_allclose(lon, longitude, atol=1e-6)
        np.testing.assert_allclose(positions[:, j, 2], 0.0, atol=1e-3)
    igso = [i for i, kind in enumerate(constellation.kinds) if kind == "IGSO"]
    start, later = constellation.ecef(1.2e9), constellation.ecef(1.2e9 + SIDEREAL_DAY)
    np.testing.assert_allclose(later[igso], start[igso], atol=1e-3)
    # The IGSO tracks cross the equator at 118 E / 95 E (ascending node at u = 0).
    j = igso[0]
    u0 = constellation.latitude0[j]
    crossing = constellation.ecef(-u0 / constellation.mean_motion[j])[j]
    assert abs(np.degrees(np.arctan2(crossing[1], crossing[0])) - 118.0) < 1e-6


def test_open_sky_visibility_at_nanjing(open_sky) -> None:
    run = simulate(open_sky, np.random.default_rng(3))
    above = run.elevation >= math.radians(5.0)
    systems = np.array(open_sky.constellation.systems)
    kinds = np.array(open_sky.constellation.kinds)
    gps = above[:, systems == "G"].sum(axis=1)
    beidou = above[:, systems == "C"].sum(axis=1)
    assert 6 <= gps.min() and gps.max() <= 12
    assert beidou.min() >= 8
    assert above[:, kinds == "GEO"].all(), "all five GEO slots (58.75-160 E) are above 5 deg at 118.8 E"
    assert not run.nlos.any()
    # With no buildings every strong satellite above the horizon mask is tracked.
    assert (run.los == (above & (run.cn0 >= open_sky.signal.tracking_threshold_dbhz))).all()


def test_canyon_cutoff_closed_form() -> None:
    view = StreetView(
        axis=np.array([0.0]),
        left=np.array([12.0]),
        right=np.array([8.0]),
        left_height=np.array([31.5]),
        right_height=np.array([21.5]),
        open_cross=np.array([False]),
        place=np.array([0]),
    )
    azimuth = np.array([[0.0, math.pi, 0.5 * math.pi, 1.5 * math.pi, math.radians(30.0)]])
    cutoff = view.cutoff(azimuth)[0]
    assert cutoff[0] == pytest.approx(0.0, abs=1e-12) and cutoff[1] == pytest.approx(0.0, abs=1e-12)
    assert cutoff[2] == pytest.approx(math.atan((21.5 - ANTENNA_HEIGHT_M) / 8.0))  # right façade (east)
    assert cutoff[3] == pytest.approx(math.atan((31.5 - ANTENNA_HEIGHT_M) / 12.0))  # left façade (west)
    assert cutoff[4] == pytest.approx(math.atan(20.0 * 0.5 / 8.0))
    crossing = StreetView(**{**view.__dict__, "open_cross": np.array([True])})
    # In a cross street the sky opens along both axes: east and west are open too.
    assert np.allclose(crossing.cutoff(azimuth)[0][:4], 0.0, atol=1e-12)


def test_urban_mask_blocks_and_reflects(urban, open_sky) -> None:
    city = simulate(urban, np.random.default_rng(5))
    sky = simulate(open_sky, np.random.default_rng(5))
    assert city.los.sum(axis=1).mean() < 0.75 * sky.los.sum(axis=1).mean()
    # LOS satellites are above their cut-off, NLOS ones below it; both above the horizon mask.
    assert np.all(city.elevation[city.los] >= city.cutoff[city.los])
    assert np.all(city.elevation[city.nlos] < city.cutoff[city.nlos])
    assert np.all(city.elevation[city.los | city.nlos] >= urban.signal.horizon_mask_rad)
    # Reflected signals are weaker and delayed (positive extra path on average).
    assert np.nanmean(city.cn0[city.nlos]) < np.nanmean(city.cn0[city.los]) - 5.0
    assert np.nanmean(city.error[city.nlos]) > np.nanmean(city.error[city.los]) + 5.0
    tracked = (city.los | city.nlos).sum(axis=1)
    assert tracked.min() >= 5


def _receiver_ecef(scenario, run) -> np.ndarray:
    lat0, lon0, h0 = scenario.site
    enu = np.stack([run.truth_east, run.truth_north, np.full(run.truth_east.size, ANTENNA_HEIGHT_M)], axis=-1)
    return enu @ enu_rotation(lat0, lon0) + geodetic_to_ecef(lat0, lon0, h0)


def test_pseudoranges_follow_the_receiver_model(urban) -> None:
    """P + c dts - sagnac_range - troposphere - simulated error is one clock bias per constellation and
    epoch (to millimetres): the Sagnac-corrected geometry the pipeline uses is the simulated one."""
    run = simulate(urban, np.random.default_rng(11))
    receivers = _receiver_ecef(urban, run)
    lat0, _, h0 = urban.site
    index = {name: j for j, name in enumerate(urban.constellation.names)}
    gnss_epochs = [epoch for epoch in run.epochs if any(isinstance(o, PseudorangeObservation) for o in epoch)]
    assert len(gnss_epochs) == run.gnss_tow.size
    for k, epoch in enumerate(gnss_epochs):
        residual: dict[str, list[float]] = {"G": [], "C": []}
        for o in epoch:
            if not isinstance(o, PseudorangeObservation):
                continue
            j = index[f"{o.system}{o.prn:02d}"]
            geometric = sagnac_range(np.asarray(o.sat_position), receivers[k])
            tropo = saastamoinen_delay(lat0, h0 + ANTENNA_HEIGHT_M, run.elevation[k, j])
            value = o.pseudorange + SPEED_OF_LIGHT * o.sat_clock - geometric - tropo - run.error[k, j]
            residual[o.system].append(float(value))
        for values in residual.values():
            if len(values) > 1:
                assert np.ptp(values) < 0.01


def test_least_squares_on_open_sky_is_metre_level(open_sky) -> None:
    run = simulate(open_sky, np.random.default_rng(2))
    receivers = _receiver_ecef(open_sky, run)
    origin = geodetic_to_ecef(*open_sky.site)
    errors = []
    for k, epoch in enumerate(e for e in run.epochs if len(e) > 1):
        prs = [o for o in epoch if isinstance(o, PseudorangeObservation)]
        batch = PseudorangeSet(
            open_sky.gps_week * 604800.0 + prs[0].t,
            tuple(o.system for o in prs),
            np.array([o.prn for o in prs]),
            np.array([o.pseudorange for o in prs]),
            np.array([o.cn0 for o in prs]),
            np.array([o.sat_position for o in prs]),
            np.array([o.sat_clock for o in prs]),
            np.full(len(prs), 1.57542e9),
        )
        solution = solve_epoch(batch, Atmosphere(None, True))
        errors.append(
            np.hypot(*(ecef_to_enu(solution.position, origin) - ecef_to_enu(receivers[k], origin))[:2])
        )
    assert np.sqrt(np.mean(np.square(errors))) < 2.0
    lat, _, _ = ecef_to_geodetic(receivers[0])
    assert abs(float(lat) - open_sky.site[0]) < 1e-5


def test_riss_noise_statistics() -> None:
    """Sensor errors minus their per-run bias have the configured standard deviations (10 % on 20 000
    samples), and the biases are drawn with the configured spread (over 200 runs)."""
    scenario = urban_scenario(short=True)
    truth = build_trajectory([Cruise(2000.0)], speed0=10.0, period=0.1)
    scenario = type(scenario)(
        **{**scenario.__dict__, "truth": truth, "gnss_every": 100000, "street": _open_view(truth.t.size)}
    )
    grade = scenario.riss
    run = simulate(scenario, np.random.default_rng(9))
    samples = np.array(
        [
            [o.wheel_speed, o.accel_x, o.accel_y, o.gyro_z]
            for e in run.epochs
            for o in e
            if isinstance(o, RissObservation)
        ]
    )
    wheel = samples[:, 0] - truth.speed
    np.testing.assert_allclose(np.std(wheel - np.mean(wheel)), grade.wheel_noise_mps, rtol=0.1)
    np.testing.assert_allclose(np.std(samples[:, 1]), grade.accel_noise_mps2, rtol=0.1)
    np.testing.assert_allclose(np.std(samples[:, 2]), grade.accel_noise_mps2, rtol=0.1)
    white = grade.gyro_arw_rad_sqrt_s / math.sqrt(0.1)
    gyro_std = math.sqrt(white**2 + grade.gyro_instability_rad_s**2)
    np.testing.assert_allclose(np.std(samples[:, 3]), gyro_std, rtol=0.1)

    biases = []
    short = urban_scenario(short=True)
    for seed in range(200):
        run = simulate(short, np.random.default_rng(seed))
        gyro = np.array([o.gyro_z for e in run.epochs for o in e if isinstance(o, RissObservation)])
        biases.append(np.mean(gyro - short.truth.yaw_rate))
    np.testing.assert_allclose(np.std(biases), grade.gyro_bias_rad_s, rtol=0.2)


def _open_view(count: int) -> StreetView:
    zeros = np.zeros(count)
    return StreetView(
        zeros, zeros + 1.0, zeros + 1.0, zeros, zeros, np.ones(count, bool), np.zeros(count, int)
    )


def test_determinism_by_seed(urban) -> None:
    first = simulate(urban, np.random.default_rng([4, 2])).observations
    again = simulate(urban, np.random.default_rng([4, 2])).observations
    other = simulate(urban, np.random.default_rng([4, 3])).observations
    assert first == again
    assert first != other


def test_turn_segment_closed_form() -> None:
    turn = Turn(4.0, 0.5 * math.pi)
    tau = np.linspace(0.0, 4.0, 4001)
    motion = turn.motion(tau, 5.0)
    assert motion.heading_change[-1] == pytest.approx(0.5 * math.pi)
    assert motion.yaw_rate[0] == pytest.approx(0.0) and motion.yaw_rate[-1] == pytest.approx(0.0, abs=1e-15)
    integral = np.sum(0.5 * (motion.yaw_rate[1:] + motion.yaw_rate[:-1]) * np.diff(tau))
    assert integral == pytest.approx(0.5 * math.pi, rel=1e-6)
    with pytest.raises(ValueError):
        Turn(4.0, 0.0)
