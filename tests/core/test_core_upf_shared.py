"""The UPF's shared linearisation (core/particles/base.py ``shared_unscented_update``): one set of sigma-point
deviations at the cloud's mean for every particle's UKF update. Exact on a linear model; on the pipeline's
own pseudorange and range-rate models it must give the per-particle update's results on the same seeds, step
after step, to a millimetre, also with a cloud tens of metres wide (as after initialisation)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.measurements.pseudorange import PseudorangeModel
from edgepos.core.measurements.range_rate import RangeRateModel
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GeodeticAnchor, GnssOnlyModel, RissInput, RissModel
from edgepos.core.particles import Cloud, Measurement, UnscentedParticleFilter
from edgepos.core.particles.base import (
    ParticleModel,
    shared_unscented_update,
    unscented_update,
    weighted_moments,
)
from edgepos.gnss.geodesy import geodetic_to_ecef

ANCHOR = GeodeticAnchor(math.radians(41.64), math.radians(2.35), 250.0)
SYSTEMS = ["G"] * 9 + ["E"] * 7


def _satellites(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities (ECEF) of satellites 20,000-26,000 km from the anchor, above 10 degrees."""
    lat, lon = ANCHOR.lat, ANCHOR.lon
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.array([-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)])
    up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    count = len(SYSTEMS)
    elevation = rng.uniform(math.radians(10.0), math.radians(85.0), count)
    azimuth = rng.uniform(0.0, 2.0 * math.pi, count)
    directions = (
        np.cos(elevation)[:, None] * (np.sin(azimuth)[:, None] * east + np.cos(azimuth)[:, None] * north)
        + np.sin(elevation)[:, None] * up
    )
    receiver = geodetic_to_ecef(ANCHOR.lat, ANCHOR.lon, ANCHOR.height)
    positions = receiver + rng.uniform(2.0e7, 2.6e7, count)[:, None] * directions
    velocities = rng.normal(0.0, 2000.0, (count, 3))
    return positions, velocities


def _measurement(
    truth: np.ndarray, sats: np.ndarray, velocities: np.ndarray, rng: np.random.Generator
) -> Measurement:
    """Pseudoranges (1 m noise) and range rates (0.1 m/s) of ``truth``, combined as gnss_tight does."""
    count = len(SYSTEMS)
    known = rng.normal(0.0, 5.0, count)
    ranges = PseudorangeModel.build(ANCHOR, sats, SYSTEMS, known, np.ones(count))
    rates = RangeRateModel.build(ANCHOR, sats, velocities, rng.normal(0.0, 1e-10, count), np.full(count, 0.1))

    def predict(states: np.ndarray) -> np.ndarray:
        return np.concatenate([ranges.predict(states), rates.predict(states)], axis=-1)

    z = predict(truth[None, :])[0] + np.concatenate(
        [rng.normal(0.0, 1.0, count), rng.normal(0.0, 0.1, count)]
    )
    variances = np.concatenate([ranges.variances(), rates.variances()])
    return Measurement(
        predict, z, variances, 0.05, np.concatenate([np.full(count, 900.0), np.full(count, 4.0)])
    )


def _truth() -> np.ndarray:
    state = np.zeros(layout.DIM)
    state[[layout.NORTH, layout.EAST, layout.UP]] = 30.0, -20.0, 2.0
    state[[layout.VE, layout.VN, layout.VU]] = 9.0, -7.0, 0.2
    state[layout.CLOCK["G"]], state[layout.CLOCK["E"]], state[layout.DRIFT] = 120.0, 95.0, 0.8
    return state


def _active(model: ParticleModel | None = None) -> np.ndarray:
    active = (model or GnssOnlyModel(ANCHOR)).active.copy()
    active[layout.CLOCK["C"]] = False
    return active


def _model(name: str) -> ParticleModel:
    """The GNSS-only model, or RISS with a car turning left at 10 m/s (its azimuth, pitch and roll active and
    wrapped: the shared deviations are taken around the cloud's circular mean)."""
    if name == "gnss_only":
        return GnssOnlyModel(ANCHOR)
    return RissModel(ANCHOR, RissInput(10.0, 0.2, 0.3, 1.5, 0.15))


@pytest.mark.parametrize(("spread_m", "model_name"), [(0.3, "gnss_only"), (30.0, "gnss_only"), (3.0, "riss")])
def test_shared_linearisation_gives_the_per_particle_upf_on_the_same_seeds(
    spread_m: float, model_name: str
) -> None:
    """Eight steps of the UPF with each particle's own sigma points and with the shared ones, on the same
    random streams: the particles agree to a millimetre, the estimate to 0.1 mm, the weights to 1 % of
    themselves and the covariance to 1e-4 of its scale (measured with the 30 m cloud: 5e-4 m, 1e-5 m, 0.1 %
    at a particle of weight 1e-5, 4e-5; the particles' measurement deviations differ by h's curvature over
    their spread, spread / 20,000 km of themselves, and by the rounding of 2e7 m ranges, 1e-6 m of a
    posterior mean, which the tight proposal turns into 5e-5 of a log-weight)."""
    rng = np.random.default_rng(21)
    model, dt = _model(model_name), 1.0
    active = _active(model)
    truth = _truth()
    truth[layout.AZIMUTH] = math.radians(179.0)  # particles on both sides of +-180 degrees
    index = np.flatnonzero(active)
    variances = np.full(layout.DIM, 4.0)  # m^2 of position and clock biases
    variances[[layout.VE, layout.VN, layout.VU, layout.DRIFT]] = 0.25
    variances[[layout.PITCH, layout.ROLL, layout.AZIMUTH]] = 1e-3
    variances[layout.GYRO_BIAS], variances[layout.WHEEL_SCALE] = 1e-8, 1e-4
    own = np.zeros((layout.DIM, layout.DIM))
    own[index, index] = variances[index]
    start = truth.copy()
    start[index] += rng.normal(0.0, np.sqrt(variances[index]))
    particles = start + np.zeros((200, layout.DIM))
    particles[:, :3] += rng.normal(0.0, spread_m, (200, 3))
    particles[:, layout.AZIMUTH] += rng.normal(0.0, 0.02, 200)
    particles[:, layout.AZIMUTH] = (particles[:, layout.AZIMUTH] + math.pi) % (2.0 * math.pi) - math.pi
    clouds = [Cloud(particles.copy(), np.full(200, -math.log(200)), own.copy()) for _ in range(2)]
    # resampling at an ESS below 90 % of the particles, so that the comparison crosses resamplings too
    filters = [UnscentedParticleFilter(0.9, shared_linearisation=False), UnscentedParticleFilter(0.9)]
    streams = [np.random.default_rng(5), np.random.default_rng(5)]
    sats, velocities = _satellites(rng)
    resampled = 0
    for _ in range(8):
        truth = model.propagate(truth[None, :], dt)[0]
        sats = sats + velocities * dt
        measurement = _measurement(truth, sats, velocities, rng)
        reference, shared = (
            f.step(c, model, dt, active, measurement, s) for f, c, s in zip(filters, clouds, streams)
        )
        weights = np.exp(reference.cloud.log_weights)
        np.testing.assert_allclose(np.exp(shared.cloud.log_weights), weights, rtol=1e-2, atol=0.0)
        np.testing.assert_allclose(shared.cloud.particles, reference.cloud.particles, rtol=0.0, atol=1e-3)
        np.testing.assert_allclose(shared.mean, reference.mean, rtol=0.0, atol=1e-4)
        block = np.ix_(index, index)  # the components the filter estimates (the others are held or derived)
        cov, expected = shared.cov[block], reference.cov[block]
        scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
        np.testing.assert_array_less(np.abs(cov - expected), 1e-4 * scale)
        assert shared.nis == pytest.approx(reference.nis, rel=1e-5)
        assert shared.resampled == reference.resampled
        resampled += shared.resampled
        clouds = [reference.cloud, shared.cloud]
    # a working filter (on the truth, resampling on the way) is what was compared
    assert resampled > 0
    assert np.linalg.norm(shared.mean[[layout.NORTH, layout.EAST, layout.UP]] - truth[:3]) < 5.0


def test_shared_update_is_the_kalman_update_on_a_linear_model() -> None:
    """For a linear h the shared deviations are every particle's: the update equals the per-particle one."""
    rng = np.random.default_rng(8)
    active = _active()
    index = np.flatnonzero(active)
    h = rng.normal(size=(6, layout.DIM)) * active
    measurement = Measurement(lambda s: s @ h.T, rng.normal(size=6), rng.uniform(0.5, 2.0, 6))
    means = rng.normal(0.0, 5.0, (7, layout.DIM))
    a = rng.normal(size=(len(index), len(index)))
    cov = a @ a.T + np.eye(len(index))
    model = GnssOnlyModel(ANCHOR)
    each = unscented_update(means.copy(), cov, model, active, layout.ANGLES, measurement)
    shared = shared_unscented_update(means.copy(), cov, model, active, layout.ANGLES, measurement, means[3])
    np.testing.assert_allclose(shared.posterior, each.posterior, atol=1e-9)
    np.testing.assert_allclose(shared.z_hat, each.z_hat, atol=1e-9)
    for i in range(len(means)):
        np.testing.assert_allclose(shared.posterior_cov, each.posterior_cov[i], atol=1e-9)
        np.testing.assert_allclose(shared.z_cov, each.z_cov[i], atol=1e-9)


def test_cloud_moments_are_computed_once_and_follow_new_arrays() -> None:
    """``Cloud.moments`` is ``weighted_moments`` of the cloud, remembered for the same arrays and angles,
    computed again for new ones, and read-only (a caller writing into it would corrupt the next)."""
    rng = np.random.default_rng(5)
    angles = layout.ANGLES
    particles = rng.normal(size=(50, len(angles)))
    log_weights = np.log(np.full(50, 1.0 / 50))
    cloud = Cloud(particles, log_weights, np.eye(len(angles)))
    first = cloud.moments(angles)
    want = weighted_moments(particles, np.exp(log_weights), angles)
    np.testing.assert_array_equal(first[0], want[0])
    np.testing.assert_array_equal(first[1], want[1])
    assert cloud.moments(angles)[0] is first[0]
    with pytest.raises(ValueError):
        first[0][0] = 1.0
    cloud.particles = particles + 1.0
    moved = cloud.moments(angles)
    assert moved[0] is not first[0]
    np.testing.assert_array_equal(moved[0], weighted_moments(cloud.particles, cloud.weights, angles)[0])
    other = np.zeros(len(angles), dtype=bool)
    assert not np.array_equal(cloud.moments(other)[0], moved[0])  # the angles count too
