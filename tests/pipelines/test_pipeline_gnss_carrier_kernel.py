"""The Hatch filter's compiled form (pipelines/gnss_carrier_kernel.py) against ``gnss.carrier.hatch_update``
on the recording with slips put in: every epoch the same smoothed ranges and counts to the bit, the same
tracks, and a restart code where the reference gives a restart reason (each kind seen)."""

from __future__ import annotations

import dataclasses

import numpy as np
from edgepos.core.observations import PseudorangeObservation
from edgepos.gnss.carrier import hatch_update
from edgepos.pipelines import gnss_satellites
from edgepos.pipelines.gnss_carrier_kernel import CODE_JUMP, CONTINUED, GAP, LOSS_OF_LOCK, SLIP, hatch_kernel
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from gnssrecording import recording_epochs

REASONS = {
    LOSS_OF_LOCK: "loss of lock (lli bit 0)",
    GAP: "s since its previous carrier phase",
    SLIP: "cycles off the Doppler's",
    CODE_JUMP: "code-carrier jump",
}


def _with_slips(epochs: list[list[PseudorangeObservation]]) -> list[list[PseudorangeObservation]]:
    """At epoch 6 the first phase loses lock (lli 1), from 9 the second jumps 40 cycles (its Doppler sees
    it), from 12 the third's code jumps 30 m (no Doppler sent: the code-carrier test), at 14 the fourth has
    no phase, and epochs 17-22 are left out (a 7 s gap)."""
    out = [list(epoch) for epoch in epochs]
    carrying = [i for i, o in enumerate(out[6]) if o.carrier_cycles is not None]
    first, second, third, fourth = carrying[:4]
    out[6][first] = dataclasses.replace(out[6][first], lli=1)
    for epoch in out[9:]:
        cycles = epoch[second].carrier_cycles
        if cycles is not None:
            epoch[second] = dataclasses.replace(epoch[second], carrier_cycles=cycles + 40.0)
    for epoch in out[12:]:
        epoch[third] = dataclasses.replace(
            epoch[third], pseudorange=epoch[third].pseudorange + 30.0, doppler_hz=None
        )
    out[14][fourth] = dataclasses.replace(out[14][fourth], carrier_cycles=None)
    return out[:17] + out[23:]


def test_the_compiled_hatch_filter_matches_the_numpy_one(monkeypatch) -> None:
    epochs, environment, _ = recording_epochs(30)
    compiled = gnss_satellites._compiled_hatch
    seen: set[int] = set()
    calls = 0

    def both(session, t, prs, phases, wavelength, settings):  # type: ignore[no-untyped-def]
        nonlocal calls
        cycles, doppler_hz, lli = phases
        tracks = session.carrier.tracks()
        expected = hatch_update(
            tracks,
            t,
            prs.sats,
            prs.pseudorange_m,
            cycles,
            wavelength,
            doppler_hz,
            lli,
            gnss_satellites._hatch_config(*settings),
        )
        n, old = len(prs), session.carrier
        reset = np.empty(n, dtype=np.int64)
        table, origin = np.empty((n + len(old), 6)), np.empty(n + len(old), dtype=np.int64)
        hatch_kernel(
            t,
            prs.pseudorange_m,
            cycles,
            wavelength,
            doppler_hz,
            lli,
            old.rows(prs.sats),
            old.table,
            np.array(settings, dtype=float),
            np.empty(n),
            np.empty(n),
            reset,
            table,
            origin,
        )
        for code, why in zip(reset.tolist(), expected.reset, strict=True):
            assert (code == CONTINUED) == (why is None)
            if why is not None:
                assert REASONS[code] in why
                seen.add(code)
        smoothed, count = compiled(session, t, prs, phases, wavelength, settings)
        assert np.array_equal(smoothed, expected.pseudorange_m)
        assert np.array_equal(count, expected.count)
        assert session.carrier.tracks() == tracks
        calls += 1
        return smoothed, count

    monkeypatch.setattr(gnss_satellites, "_compiled_hatch", both)
    pipeline = GnssTightPipeline()
    state = pipeline.create(pipeline.resolve_options({"filter": "ukf"}), None)
    for epoch in _with_slips(epochs):
        _, state = pipeline.process(state, epoch, environment)
    assert calls == 24
    assert seen == set(REASONS)
