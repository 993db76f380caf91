"""The phase differences' compiled forms (pipelines/gnss_tdcp_kernel.py) against their numpy references, on
the recording with slips put in: the same rows and reasons for every epoch, the model terms, the rotation, the
displacement model's noise and the cloud's move to the bit, the displacement to rounding."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from edgepos.core.motion import riss as layout
from edgepos.core.observations import PseudorangeObservation
from edgepos.core.particles import Cloud
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT
from edgepos.gnss.tdcp import model_terms
from edgepos.pipelines import gnss_tdcp, gnss_tight
from edgepos.pipelines.gnss_tdcp_kernel import move_kernel, terms_kernel
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from gnssrecording import recording_epochs


def _with_slips(epochs: list[list[PseudorangeObservation]]) -> list[list[PseudorangeObservation]]:
    """At epoch 8 the first phase loses lock (lli 1), at 12 the second jumps 40 cycles (its Doppler sees it),
    at 16 the third has no phase (so at 17 it has none at the previous epoch), at 18 the last phase jumps 3
    cycles with no Doppler sent (the fit leaves it out), and at 21 all but four lose lock (too few)."""
    out = [list(epoch) for epoch in epochs]
    carrying = [i for i, o in enumerate(out[8]) if o.carrier_cycles is not None]
    first, second, third = carrying[:3]
    out[8][first] = dataclasses.replace(out[8][first], lli=1)
    for epoch in out[12:]:
        cycles = epoch[second].carrier_cycles
        if cycles is not None:
            epoch[second] = dataclasses.replace(epoch[second], carrier_cycles=cycles + 40.0)
    out[16][third] = dataclasses.replace(out[16][third], carrier_cycles=None)
    last = max(i for i, o in enumerate(out[18]) if o.carrier_cycles is not None)
    cycles = out[18][last].carrier_cycles
    assert cycles is not None
    out[18][last] = dataclasses.replace(out[18][last], carrier_cycles=cycles + 3.0, doppler_hz=None)
    phased = [i for i, o in enumerate(out[21]) if o.carrier_cycles is not None]
    for i in phased[4:]:
        out[21][i] = dataclasses.replace(out[21][i], lli=1)
    return out


def test_the_compiled_step_matches_the_numpy_one(monkeypatch) -> None:
    """Each epoch's ``compiled_step`` (one kernel call) against ``reference_step`` on the same inputs, at the
    epoch and beyond the gap: the same reasons; the fit to its rounding; and from the compiled fit on, the
    rotation, the displacement model's noise and the moved cloud (particles, covariance, moments) to the
    bit against the numpy forms (``rotated``, ``shift_cloud``)."""
    epochs, environment, _ = recording_epochs(24)
    compiled = gnss_tdcp.compiled_step
    seen: list[str] = []
    fits = 0

    def both(history, t, prs, phases, atmosphere, config, anchor, mean, cloud, q):  # type: ignore[no-untyped-def]
        nonlocal fits
        assert history.receiver is not None and history.t is not None
        given, results = q.copy(), []
        for when in (t, history.t + config.max_gap_s + 1.0):  # this epoch, and one beyond the gap
            args = (history, when, prs, phases, atmosphere, config, anchor, mean, cloud)
            monkeypatch.setenv("EDGEPOS_NUMBA", "0")
            expected_q = given.copy()
            expected, expected_cloud, expected_noise = gnss_tdcp.reference_step(*args, expected_q)
            terms = model_terms(
                np.array(history.receiver),
                prs.sat_position,
                prs.sat_clock_s,
                np.full(len(prs), 2.5),
                np.full(len(prs), 1.5),
                SPEED_OF_LIGHT,
            )
            monkeypatch.setenv("EDGEPOS_NUMBA", "1")
            got_q = given.copy()
            got, got_cloud, got_noise = compiled(*args, got_q)
            compiled_terms = np.empty(len(prs))
            terms_kernel(
                np.array(history.receiver),
                prs.sat_position,
                prs.sat_clock_s,
                np.full(len(prs), 2.5),
                np.full(len(prs), 1.5),
                OMEGA_EARTH,
                SPEED_OF_LIGHT,
                compiled_terms,
            )
            assert np.array_equal(compiled_terms, terms)
            results.append((got, got_cloud, got_noise, got_q))
            assert got.reasons == expected.reasons and got.why == expected.why
            seen.extend(str(r) for r in expected.reasons)
            if expected.d is None:
                assert got.d is None and got.cov is None and got_cloud is None and got_noise is None
                assert np.array_equal(got_q, given) and np.array_equal(expected_q, given)
                continue
            assert got.d is not None and got.cov is not None and expected.cov is not None
            assert expected_cloud is not None and got_cloud is not None and got_noise is not None
            assert np.allclose(got.d, expected.d, rtol=0.0, atol=1e-9)
            assert np.allclose(got.cov, expected.cov, rtol=1e-9, atol=1e-15)
            assert got.clock_m == pytest.approx(expected.clock_m, abs=1e-9)
            assert np.allclose(got_cloud.particles, expected_cloud.particles, rtol=0.0, atol=1e-8)
            assert expected_noise is not None
            assert np.allclose(got_noise, expected_noise, rtol=1e-9, atol=1e-15)
            # the compiled fit's displacement through the numpy forms: the kernel's bits
            lat = float(anchor[0] + mean[layout.NORTH] / anchor[3])
            lon = float(anchor[1] + mean[layout.EAST] / anchor[4])
            step, noise = gnss_tdcp.rotated(gnss_tdcp.north_east_up(lat, lon), got.d, got.cov)
            assert np.array_equal(got_noise, noise) and np.array_equal(noise, noise.T)
            assert np.array_equal(got_q, gnss_tdcp.displacement_noise(given.copy(), noise))
            numpy_cloud = gnss_tdcp.shift_cloud(cloud, step, when - history.t)
            _assert_same_cloud(got_cloud, numpy_cloud)
            fits += 1
        got, got_cloud, got_noise, got_q = results[0]  # the epoch's own: the pipeline goes on with it
        q[...] = got_q
        return got, got_cloud, got_noise

    monkeypatch.setattr(gnss_tdcp, "compiled_step", both)
    remember = gnss_tdcp.remember_phases
    remembered = 0

    def both_histories(session, *args):  # type: ignore[no-untyped-def]
        nonlocal remembered
        monkeypatch.setenv("EDGEPOS_NUMBA", "0")
        remember(session, *args)
        expected = session.tdcp
        monkeypatch.setenv("EDGEPOS_NUMBA", "1")
        remember(session, *args)
        if expected.receiver is None:
            assert session.tdcp == expected
            return
        # the receiver by geodetic_to_ecef's formula (numpy's sin and cos against libm's: the same bits
        # where they agree, as on the machine this was written on) and the terms there
        assert session.tdcp.t == expected.t and session.tdcp.phases.keys() == expected.phases.keys()
        assert np.allclose(session.tdcp.receiver, expected.receiver, rtol=0.0, atol=1e-6)
        got = np.array([session.tdcp.phases[s] for s in expected.phases])
        assert np.allclose(got, np.array(list(expected.phases.values())), rtol=0.0, atol=1e-6)
        remembered += 1

    monkeypatch.setattr(gnss_tight, "remember_phases", both_histories)
    pipeline = GnssTightPipeline()
    state = pipeline.create(pipeline.resolve_options({"filter": "ukf", "carrier_smoothing": "tdcp"}), None)
    for epoch in _with_slips(epochs):
        _, state = pipeline.process(state, epoch, environment)
    assert fits >= 15 and remembered >= 20
    for reason in (
        "loss of lock (lli bit 0)",
        "no carrier phase at the previous epoch",
        "s since the previous epoch (max gap 5 s)",
        "cycles off the Doppler's over 1 s",
        "m off the displacement fit",
        "continuous phases, fewer than 5",
    ):
        assert any(reason in text for text in seen), reason


def _assert_same_cloud(got: Cloud, expected: Cloud) -> None:
    """The same particles, weights, covariance and remembered moments, to the bit."""
    assert np.array_equal(got.particles, expected.particles)
    assert got.log_weights is expected.log_weights
    assert np.array_equal(got.cov, expected.cov) and np.array_equal(got.cov, got.cov.T)
    known, reference = got.known_moments(layout.ANGLES), expected.known_moments(layout.ANGLES)
    assert (known is None) == (reference is None)
    if known is not None and reference is not None:
        assert np.array_equal(known[0], reference[0]) and np.array_equal(known[1], reference[1])


@pytest.mark.parametrize("dt", [1.0, 0.2, 1.3])
@pytest.mark.parametrize("with_moments", [True, False])
def test_the_compiled_move_of_the_cloud_is_the_numpy_one_to_the_bit(dt, with_moments) -> None:
    rng = np.random.default_rng(7)
    root = rng.normal(size=(layout.DIM, layout.DIM)) * rng.uniform(0.01, 100.0, layout.DIM)
    cloud = Cloud(rng.normal(0.0, 20.0, (50, layout.DIM)), np.full(50, -np.log(50.0)), root @ root.T)
    if with_moments:
        cloud.moments(layout.ANGLES)
    step = np.array([3.1, -12.7, 0.43])
    known = cloud.known_moments(layout.ANGLES)
    mean, moments_cov = (np.zeros(0), np.zeros((0, 0))) if known is None else known
    particles, cov = np.empty_like(cloud.particles), np.empty_like(cloud.cov)
    out_mean, out_cov = np.empty_like(mean), np.empty_like(moments_cov)
    move_kernel(cloud.particles, cloud.cov, mean, moments_cov, step, dt, particles, cov, out_mean, out_cov)
    compiled_cloud = Cloud(particles, cloud.log_weights, cov)
    if known is not None:
        compiled_cloud.remember_moments(layout.ANGLES, out_mean, out_cov)
    numpy_cloud = gnss_tdcp.shift_cloud(cloud, step, dt)
    _assert_same_cloud(compiled_cloud, numpy_cloud)
    # the map itself: T C T^T with T the identity but -dt from each velocity to its position
    transform = np.eye(layout.DIM)
    transform[[layout.NORTH, layout.EAST, layout.UP], [layout.VN, layout.VE, layout.VU]] = -dt
    assert np.allclose(compiled_cloud.cov, transform @ cloud.cov @ transform.T, rtol=1e-12, atol=1e-9)
