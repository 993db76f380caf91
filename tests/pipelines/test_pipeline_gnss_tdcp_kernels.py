"""The phase differences' compiled forms (pipelines/gnss_tdcp_kernel.py) against their numpy references, on
the recording with slips put in: the same rows and reasons for every epoch, the model terms and the cloud's
move to the bit, the displacement to rounding."""

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
from edgepos.pipelines.gnss_tdcp_kernel import terms_kernel
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from gnssrecording import recording_epochs


def _with_slips(epochs: list[list[PseudorangeObservation]]) -> list[list[PseudorangeObservation]]:
    """At epoch 8 the first phase loses lock (lli 1), at 12 the second jumps 40 cycles (its Doppler sees it),
    at 16 the third has no phase (so at 17 it has none at the previous epoch)."""
    out = [list(epoch) for epoch in epochs]
    carrying = [i for i, o in enumerate(out[8]) if o.carrier_cycles is not None]
    first, second, third = carrying[:3]
    out[8][first] = dataclasses.replace(out[8][first], lli=1)
    for epoch in out[12:]:
        cycles = epoch[second].carrier_cycles
        if cycles is not None:
            epoch[second] = dataclasses.replace(epoch[second], carrier_cycles=cycles + 40.0)
    out[16][third] = dataclasses.replace(out[16][third], carrier_cycles=None)
    return out


def test_the_compiled_displacement_matches_the_numpy_one(monkeypatch) -> None:
    epochs, environment, _ = recording_epochs(24)
    reference = gnss_tdcp.epoch_displacement
    seen: list[str] = []
    fits = 0

    def both(history, t, prs, phases, delays, config):  # type: ignore[no-untyped-def]
        nonlocal fits
        assert history.receiver is not None and history.t is not None
        for when in (t, history.t + config.max_gap_s + 1.0):  # this epoch, and one beyond the gap
            monkeypatch.setenv("EDGEPOS_NUMBA", "0")
            expected = reference(history, when, prs, phases, delays, config)
            terms = model_terms(
                np.array(history.receiver),
                prs.sat_position,
                prs.sat_clock_s,
                delays[1],
                delays[0],
                SPEED_OF_LIGHT,
            )
            monkeypatch.setenv("EDGEPOS_NUMBA", "1")
            got = reference(history, when, prs, phases, delays, config)
            compiled_terms = np.empty(len(prs))
            terms_kernel(
                np.array(history.receiver),
                prs.sat_position,
                prs.sat_clock_s,
                delays[1],
                delays[0],
                OMEGA_EARTH,
                SPEED_OF_LIGHT,
                compiled_terms,
            )
            assert np.array_equal(compiled_terms, terms)
            assert got.reasons == expected.reasons and got.why == expected.why
            seen.extend(str(r) for r in expected.reasons)
            if expected.d is None:
                assert got.d is None and got.cov is None
                continue
            assert got.d is not None and got.cov is not None and expected.cov is not None
            assert np.allclose(got.d, expected.d, rtol=0.0, atol=1e-9)
            assert np.allclose(got.cov, expected.cov, rtol=1e-9, atol=1e-15)
            assert got.clock_m == pytest.approx(expected.clock_m, abs=1e-9)
            fits += 1
        return got

    monkeypatch.setattr(gnss_tdcp, "epoch_displacement", both)
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
    ):
        assert any(reason in text for text in seen), reason


@pytest.mark.parametrize("dt", [1.0, 0.2, 1.3])
def test_the_compiled_move_of_the_cloud_is_the_numpy_one_to_the_bit(monkeypatch, dt) -> None:
    rng = np.random.default_rng(7)
    root = rng.normal(size=(layout.DIM, layout.DIM)) * rng.uniform(0.01, 100.0, layout.DIM)
    cloud = Cloud(rng.normal(0.0, 20.0, (50, layout.DIM)), np.full(50, -np.log(50.0)), root @ root.T)
    cloud.moments(layout.ANGLES)
    step = np.array([3.1, -12.7, 0.43])
    moved = {}
    for setting in ("0", "1"):
        monkeypatch.setenv("EDGEPOS_NUMBA", setting)
        moved[setting] = gnss_tdcp.shift_cloud(cloud, step, dt)
    numpy_cloud, compiled_cloud = moved["0"], moved["1"]
    assert np.array_equal(compiled_cloud.particles, numpy_cloud.particles)
    assert np.array_equal(compiled_cloud.cov, numpy_cloud.cov)
    assert np.array_equal(compiled_cloud.cov, compiled_cloud.cov.T)
    known, expected = compiled_cloud.known_moments(layout.ANGLES), numpy_cloud.known_moments(layout.ANGLES)
    assert known is not None and expected is not None
    assert np.array_equal(known[0], expected[0]) and np.array_equal(known[1], expected[1])
    # the map itself: T C T^T with T the identity but -dt from each velocity to its position
    transform = np.eye(layout.DIM)
    transform[[layout.NORTH, layout.EAST, layout.UP], [layout.VN, layout.VE, layout.VU]] = -dt
    assert np.allclose(compiled_cloud.cov, transform @ cloud.cov @ transform.T, rtol=1e-12, atol=1e-9)
