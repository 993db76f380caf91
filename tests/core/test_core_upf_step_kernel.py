"""The UPF's compiled step with the GNSS-only model (core/particles/upf_step_kernel.py) against the numpy step
it replaces (``UnscentedParticleFilter._proposal`` and the time update before it), on the pipeline's own
pseudorange and range-rate models; where it declines, the numpy step runs on the random generator as it was."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import compiled
from edgepos.core.errors import NumericalError
from edgepos.core.measurements.pseudorange import PseudorangeModel
from edgepos.core.measurements.range_rate import RangeRateModel
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GeodeticAnchor, GnssOnlyModel, RissInput, RissModel
from edgepos.core.particles import (
    Cloud,
    Measurement,
    UnscentedParticleFilter,
    upf_resample_kernel,
    upf_step_kernel,
)
from edgepos.core.particles import upf as upf_module
from edgepos.core.particles.base import normalise, regularised_resample, weighted_moments
from edgepos.core.particles.upf_step_kernel import Proposal, compiled_proposal
from edgepos.gnss.geodesy import geodetic_to_ecef

pytestmark = pytest.mark.skipif(
    not compiled.compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)"
)

ANCHOR = GeodeticAnchor(math.radians(41.64), math.radians(2.35), 250.0)
SYSTEMS = ["G"] * 8 + ["C"] * 6 + ["E"] * 6


def _measurement(rng: np.random.Generator, truth: np.ndarray, outliers: float) -> Measurement:
    """Pseudoranges (2 m noise) and range rates (0.2 m/s) of ``truth`` from satellites 20,000-26,000 km
    away, as gnss_tight combines them."""
    count = len(SYSTEMS)
    lat, lon = ANCHOR.lat, ANCHOR.lon
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.array([-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)])
    up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    elevation = rng.uniform(math.radians(10.0), math.radians(85.0), count)
    azimuth = rng.uniform(0.0, 2.0 * math.pi, count)
    directions = (
        np.cos(elevation)[:, None] * (np.sin(azimuth)[:, None] * east + np.cos(azimuth)[:, None] * north)
        + np.sin(elevation)[:, None] * up
    )
    receiver = geodetic_to_ecef(ANCHOR.lat, ANCHOR.lon, ANCHOR.height)
    sats = receiver + rng.uniform(2.0e7, 2.6e7, count)[:, None] * directions
    velocities = rng.normal(0.0, 2000.0, (count, 3))
    ranges = PseudorangeModel.build(ANCHOR, sats, SYSTEMS, rng.normal(0.0, 5.0, count), np.full(count, 2.0))
    rates = RangeRateModel.build(ANCHOR, sats, velocities, rng.normal(0.0, 1e-10, count), np.full(count, 0.2))

    def predict(states: np.ndarray) -> np.ndarray:
        return np.concatenate([ranges.predict(states), rates.predict(states)], axis=-1)

    noise = np.concatenate([rng.normal(0.0, 2.0, count), rng.normal(0.0, 0.2, count)])
    variances = np.concatenate([ranges.variances(), rates.variances()])
    outlier_variance = np.concatenate([np.full(count, 900.0), np.full(count, 4.0)])
    return Measurement(
        predict,
        predict(truth[None, :])[0] + noise,
        variances,
        outliers,
        outlier_variance if outliers else 0.0,
    )


def _cloud(rng: np.random.Generator, spread_m: float, count: int = 200) -> tuple[Cloud, np.ndarray]:
    """A cloud about a car at 12 m/s heading 179 deg (particles on both sides of +-180 deg), with its own
    covariance on the GNSS-only model's components; and the truth it is about."""
    truth = np.zeros(layout.DIM)
    truth[[layout.NORTH, layout.EAST, layout.UP]] = 30.0, -20.0, 2.0
    heading = math.radians(179.0)
    truth[[layout.VE, layout.VN, layout.VU]] = 12.0 * math.sin(heading), 12.0 * math.cos(heading), 0.1
    truth[[layout.CLOCK["G"], layout.CLOCK["C"], layout.CLOCK["E"], layout.DRIFT]] = 120.0, 80.0, 95.0, 0.8
    truth = GnssOnlyModel.complete(truth[None, :])[0]
    index = np.flatnonzero(GnssOnlyModel(ANCHOR).active)
    variances = np.full(layout.DIM, 4.0)
    variances[[layout.VE, layout.VN, layout.VU, layout.DRIFT]] = 0.25
    own = np.zeros((layout.DIM, layout.DIM))
    own[index, index] = variances[index]
    own[layout.NORTH, layout.EAST] = own[layout.EAST, layout.NORTH] = 1.5  # correlated, as after updates
    particles = truth + np.zeros((count, layout.DIM))
    particles[:, index] += rng.normal(0.0, 1.0, (count, len(index))) * np.sqrt(variances[index])
    particles[:, :3] += rng.normal(0.0, spread_m, (count, 3))
    particles = GnssOnlyModel.complete(particles)
    log_weights = rng.normal(0.0, 0.5, count)
    log_weights -= math.log(float(np.sum(np.exp(log_weights))))
    return Cloud(particles, log_weights, own), truth


def _numpy_proposal(
    upf: UnscentedParticleFilter,
    cloud: Cloud,
    model: GnssOnlyModel,
    dt: float,
    active: np.ndarray,
    measurement: Measurement,
    rng: np.random.Generator,
) -> Proposal:
    reference, predicted_cov = upf_module._own_prediction(cloud, model, dt, active)
    centres = model.complete(upf_module.wrap(model.propagate(cloud.particles, dt), layout.ANGLES))
    return upf._proposal(cloud, model, active, measurement, rng, centres, reference, predicted_cov)


@pytest.mark.parametrize(("spread_m", "outliers", "seed"), [(0.3, 0.05, 1), (30.0, 0.05, 2), (3.0, 0.0, 3)])
def test_compiled_proposal_is_the_numpy_one(spread_m: float, outliers: float, seed: int) -> None:
    """Every array of the proposal from the same cloud and the same random stream: states to 1e-8 m (the
    clocks' tens of metres and the ranges' 2e7 m rounded in another order), covariances and factors to
    1e-9 of their scale, the predicted measurements to 1e-6 m; the stream left where the numpy step leaves
    it."""
    rng = np.random.default_rng(seed)
    cloud, truth = _cloud(rng, spread_m)
    model = GnssOnlyModel(ANCHOR)
    active = model.active.copy()
    measurement = _measurement(rng, model.propagate(truth[None, :], 1.0)[0], outliers)
    upf = UnscentedParticleFilter()
    streams = [np.random.default_rng(seed + 10), np.random.default_rng(seed + 10)]
    kernel = compiled_proposal(cloud, model, 1.0, active, measurement, streams[0], upf.spread_fraction)
    numpy = _numpy_proposal(upf, cloud, model, 1.0, active, measurement, streams[1])
    assert kernel is not None
    assert streams[0].bit_generator.state == streams[1].bit_generator.state
    for name in ("centres", "sampled", "particles", "prior_deviation", "proposal_deviation"):
        np.testing.assert_allclose(getattr(kernel, name), getattr(numpy, name), rtol=0.0, atol=1e-8)
    for name in ("posterior_cov", "proposal_chol", "prior_chol", "z_cov"):
        want = getattr(numpy, name)
        np.testing.assert_allclose(getattr(kernel, name), want, rtol=0.0, atol=1e-9 * np.abs(want).max())
    np.testing.assert_allclose(kernel.z_hat, numpy.z_hat, rtol=0.0, atol=1e-6)
    # the comparison is of a real update: the proposal moved the particles and the draws spread them
    assert np.abs(numpy.sampled - numpy.centres)[:, : layout.UP + 1].max() > 0.1
    assert np.ptp(numpy.proposal_deviation[:, 0]) > 0.01


@pytest.mark.parametrize("outliers", [0.0, 0.05])
def test_compiled_weights_are_the_numpy_ones(outliers: float) -> None:
    """The weights, NIS, own covariance, moments and effective sample size of one proposal: log-weights to
    1e-9, the NIS to 1e-7 of itself, the own covariance exactly (copies and one product), the moments to
    1e-9 m (m^2) and the ESS to 1e-9 of itself."""
    rng = np.random.default_rng(11)
    cloud, truth = _cloud(rng, 3.0)
    model = GnssOnlyModel(ANCHOR)
    active = model.active.copy()
    measurement = _measurement(rng, model.propagate(truth[None, :], 1.0)[0], outliers)
    upf = UnscentedParticleFilter()
    proposal = compiled_proposal(cloud, model, 1.0, active, measurement, np.random.default_rng(1), 0.02)
    assert proposal is not None
    residual = measurement.z - measurement.predict(proposal.sampled)
    kernel = upf_step_kernel.compiled_weights(
        cloud.log_weights, measurement, residual, proposal, cloud.cov, active, upf.spread_fraction
    )
    numpy = upf._numpy_weights(cloud, measurement, residual, proposal, active)
    assert kernel is not None
    np.testing.assert_allclose(kernel.log_weights, numpy.log_weights, rtol=0.0, atol=1e-9)
    assert kernel.score == pytest.approx(numpy.score, rel=1e-7)
    np.testing.assert_array_equal(kernel.own, numpy.own)
    np.testing.assert_allclose(kernel.mean, numpy.mean, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(kernel.spread, numpy.spread, rtol=0.0, atol=1e-9)
    assert kernel.ess == pytest.approx(numpy.ess, rel=1e-9)
    assert np.ptp(numpy.log_weights) > 1.0  # the weights differ: the comparison is not of constants


def test_compiled_step_is_the_numpy_step(monkeypatch: pytest.MonkeyPatch) -> None:
    """Six whole steps (weights, estimate, resampling) with the kernels and with EDGEPOS_NUMBA=0 from the
    same cloud and seeds: the same particles to 1e-6 m, weights to 1e-7, estimate to 1e-7 m, NIS to 1e-7 of
    itself (a 40 x 40 innovation covariance solved by Cholesky against numpy's LU: 1.5e-9 measured)."""
    rng = np.random.default_rng(4)
    cloud, truth = _cloud(rng, 3.0)
    model = GnssOnlyModel(ANCHOR)
    upf = UnscentedParticleFilter(resample_threshold=0.9)
    clouds, streams = [cloud, cloud], [np.random.default_rng(9), np.random.default_rng(9)]
    resampled = 0
    for _ in range(6):
        truth = model.propagate(truth[None, :], 1.0)[0]
        measurement = _measurement(rng, truth, 0.05)
        results = []
        for on, c, s in zip(("1", "0"), clouds, streams, strict=True):
            monkeypatch.setenv("EDGEPOS_NUMBA", on)
            results.append(upf.step(c, model, 1.0, model.active.copy(), measurement, s))
        kernel, numpy = results
        np.testing.assert_allclose(kernel.cloud.particles, numpy.cloud.particles, rtol=0.0, atol=1e-6)
        np.testing.assert_allclose(
            np.exp(kernel.cloud.log_weights), np.exp(numpy.cloud.log_weights), atol=1e-7
        )
        np.testing.assert_allclose(kernel.mean, numpy.mean, rtol=0.0, atol=1e-7)
        np.testing.assert_allclose(kernel.cov, numpy.cov, rtol=1e-7, atol=1e-9)
        assert kernel.nis == pytest.approx(numpy.nis, rel=1e-7)
        assert kernel.resampled == numpy.resampled
        resampled += kernel.resampled
        clouds = [kernel.cloud, numpy.cloud]
    assert resampled > 0  # the comparison crossed resamplings
    assert np.linalg.norm(numpy.mean[: layout.UP + 1] - truth[: layout.UP + 1]) < 5.0


def test_declines_where_the_numpy_step_decides(monkeypatch: pytest.MonkeyPatch) -> None:
    """None, the stream untouched, for another motion model, a cloud without a covariance of its own (the
    numpy step's point prior), a measurement whose innovation covariance has no Cholesky factor, and with
    EDGEPOS_NUMBA=0."""
    rng = np.random.default_rng(6)
    cloud, truth = _cloud(rng, 1.0)
    gnss_only = GnssOnlyModel(ANCHOR)
    measurement = _measurement(rng, truth, 0.05)
    stream = np.random.default_rng(3)
    start = stream.bit_generator.state

    def declined(model: object, c: Cloud, m: Measurement) -> bool:
        active = gnss_only.active.copy()
        result = compiled_proposal(c, model, 1.0, active, m, stream, 0.02)
        return result is None and stream.bit_generator.state == start

    riss = RissModel(ANCHOR, RissInput(10.0, 0.2, 0.3, 1.5, 0.15))
    assert declined(riss, cloud, measurement)
    point = Cloud(cloud.particles, cloud.log_weights, np.zeros((layout.DIM, layout.DIM)))
    assert declined(gnss_only, point, measurement)
    singular = Measurement(measurement.predict, measurement.z, -np.abs(measurement.variances), 0.05, 900.0)
    assert declined(gnss_only, cloud, singular)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    assert declined(gnss_only, cloud, measurement)


def test_a_declined_update_leaves_the_stream_and_the_decision_to_numpy(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Noise-free measurements (an innovation covariance of rank 2k + 1 < m): the update's kernel, which
    runs after the draws, declines; the stream is put back, and the step is the numpy one, which finds
    the posterior covariance indefinite and raises, with the kernels as without them."""
    rng = np.random.default_rng(7)
    cloud, truth = _cloud(rng, 1.0)
    model = GnssOnlyModel(ANCHOR)
    measurement = _measurement(rng, truth, 0.05)
    exact = Measurement(measurement.predict, measurement.z, np.full(len(measurement.z), 1e-30), 0.05, 900.0)
    stream, again = np.random.default_rng(2), np.random.default_rng(2)
    assert compiled_proposal(cloud, model, 1.0, model.active.copy(), exact, stream, 0.02) is None
    assert stream.bit_generator.state == again.bit_generator.state
    for on in ("1", "0"):
        monkeypatch.setenv("EDGEPOS_NUMBA", on)
        with pytest.raises(NumericalError, match="indefinite"):
            UnscentedParticleFilter().step(cloud, model, 1.0, model.active.copy(), exact, stream)


def test_warm_up_compiles_the_signature_the_step_uses() -> None:
    """After the warm-up a step of the pipeline's kind, resampling, compiles nothing new: one signature per
    kernel."""
    upf_step_kernel.warm_up()
    rng = np.random.default_rng(8)
    cloud, truth = _cloud(rng, 1.0)
    model = GnssOnlyModel(ANCHOR)
    UnscentedParticleFilter(resample_threshold=1.01).step(
        cloud, model, 1.0, model.active.copy(), _measurement(rng, truth, 0.05), rng
    )
    upf_resample_kernel.warm_up()
    kernels = (
        upf_step_kernel.time_update_kernel,
        upf_step_kernel.update_kernel,
        upf_step_kernel.weigh_kernel,
        upf_resample_kernel.resample_kernel,
    )
    for kernel in kernels:
        assert len(kernel.signatures) == 1


@pytest.mark.parametrize("angles_active", [False, True])
def test_compiled_resampling_is_the_numpy_one(angles_active: bool) -> None:
    """``upf_resample_kernel.compiled_resample`` against ``base.regularised_resample`` from the same
    weighted cloud and stream: the same particles to 1e-9 (the angles wrapped alike, with a heading near
    +-180 deg and the angles among the sampled components or not), the stream left where numpy leaves it."""
    rng = np.random.default_rng(12)
    cloud, _ = _cloud(rng, 3.0)
    log_weights = normalise(rng.normal(0.0, 2.0, len(cloud.particles)))  # an ESS well below half
    active = GnssOnlyModel(ANCHOR).active.copy()
    active[[layout.AZIMUTH, layout.PITCH]] = angles_active
    mean, cov = weighted_moments(cloud.particles, np.exp(log_weights), layout.ANGLES)
    streams = [np.random.default_rng(4), np.random.default_rng(4)]
    kernel = upf_resample_kernel.compiled_resample(
        cloud.particles, log_weights, mean, cov, active, layout.ANGLES, streams[0]
    )
    numpy = regularised_resample(cloud.particles, log_weights, active, layout.ANGLES, streams[1])
    assert kernel is not None
    assert streams[0].bit_generator.state == streams[1].bit_generator.state
    np.testing.assert_allclose(kernel, numpy, rtol=0.0, atol=1e-9)
    assert len({tuple(row) for row in np.round(numpy[:, :3], 6)}) > 100  # spread, not copies
    assert np.abs(numpy[:, layout.AZIMUTH]).max() > 3.0  # headings on both sides of +-180 deg


def test_compiled_resampling_declines_a_degenerate_kernel() -> None:
    """A cloud of one repeated particle (no spread, the kernel's covariance zero): None and the stream as
    it was; the numpy form decides."""
    particles = np.zeros((20, layout.DIM))
    stream = np.random.default_rng(5)
    start = stream.bit_generator.state
    active = GnssOnlyModel(ANCHOR).active.copy()
    log_weights = np.full(20, -math.log(20.0))
    result = upf_resample_kernel.compiled_resample(
        particles,
        log_weights,
        np.zeros(layout.DIM),
        np.zeros((layout.DIM, layout.DIM)),
        active,
        layout.ANGLES,
        stream,
    )
    assert result is None and stream.bit_generator.state == start
