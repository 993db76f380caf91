"""gnss_tight with carrier phase on the real recording (tests/data/gnss-rover): Hatch smoothing is not worse
than raw code on either half, the smoothing state lives in the session and round-trips its bytes, the
option off ignores the carrier, states stored before carrier phase still decode, and bad carrier fields are
refused naming the field."""

from __future__ import annotations

import dataclasses

import pytest
from edgepos.core import state as state_format
from edgepos.core.observations import PseudorangeObservation
from edgepos.eval.gnss_rinex import evaluate
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
from edgepos.pipelines.base import PipelineInputError, StaticEnvironment
from edgepos.pipelines.gnss_recording import epoch_pseudoranges
from edgepos.pipelines.gnss_session import decode_session
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from gnssrecording import run_ukf

DATA = "tests/data/gnss-rover/"
FILES = (DATA + "rover-0-5min.rnx", DATA + "broadcast-nav.rnx", DATA + "reference-0-5min.csv")


def test_carrier_smoothing_is_not_worse_on_either_half() -> None:
    """UKF over all 300 epochs, scored per half, with the Hatch filter alone (the default adds the phase
    differences: tests/pipelines/test_pipeline_gnss_tdcp.py). Measured (docs/gnss.md): first half 2.85 ->
    2.07 m, second half 3.32 -> 2.71 m with the carrier; the test asks only for not worse, with 5 cm of slack."""
    options = {"filter": "ukf", "seed": 1, "carrier_smoothing": "hatch"}
    for half in ((0, 150), (150, 300)):
        with_carrier = evaluate(*FILES, options=options, score_epochs=half, carrier=True)
        without = evaluate(*FILES, options=options, score_epochs=half, carrier=False)
        assert with_carrier["fixes"] == without["fixes"] == 150
        assert with_carrier["horizontal_rms_m"] <= without["horizontal_rms_m"] + 0.05
        assert with_carrier["carrier_sent"] and with_carrier["carrier_smoothing"] == "hatch"


@pytest.fixture(scope="module")
def recording() -> tuple[list[list[PseudorangeObservation]], StaticEnvironment]:
    codes = {s: DEFAULT_CODES[s] for s in "GC"}
    environment = StaticEnvironment(
        navigation=Ephemerides.from_navigation(read_navigation(DATA + "broadcast-nav.rnx"))
    )
    epochs = []
    for number, epoch in enumerate(read_epochs(FILES[0], codes)):
        if number >= 8:
            break
        epochs.append(epoch_pseudoranges(epoch))
    return epochs, environment


def test_the_smoothing_lives_in_the_session_and_round_trips(recording) -> None:
    epochs, environment = recording
    fixes, state = run_ukf(epochs, environment, {})
    session = decode_session(state)
    carrying = {f"{o.system}{o.prn:02d}" for o in epochs[-1] if o.carrier_cycles is not None}
    assert carrying and set(session.carrier.sats) >= carrying
    assert max(track.count for track in session.carrier.tracks().values()) == len(epochs)
    assert session.to_bytes() == state
    # Off: the carrier is ignored (the same fixes as without it) and no track is kept.
    off, off_state = run_ukf(epochs, environment, {"carrier_smoothing": "off"})
    stripped = [[dataclasses.replace(o, carrier_cycles=None, lli=None) for o in epoch] for epoch in epochs]
    plain, _ = run_ukf(stripped, environment, {})
    assert len(decode_session(off_state).carrier) == 0
    assert [(f.x, f.y) for f in off] == [(f.x, f.y) for f in plain]
    assert [(f.x, f.y) for f in fixes] != [(f.x, f.y) for f in plain]


def test_states_stored_before_carrier_phase_decode_with_no_tracks(recording) -> None:
    epochs, environment = recording
    _, state = run_ukf(epochs[:3], environment, {})
    meta, arrays = state_format.unpack(state)
    del meta["carrier_sats"], arrays["carrier"]
    old = decode_session(state_format.pack(meta, arrays))
    assert len(old.carrier) == 0
    pipeline = GnssTightPipeline()
    (fix,), _ = pipeline.process(old.to_bytes(), epochs[3], environment)
    assert fix.status == "tracking"


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"carrier_cycles": float("nan")}, "carrier_cycles"),
        ({"carrier_cycles": float("inf")}, "carrier_cycles"),
        ({"carrier_cycles": 1.0e10}, "carrier_cycles"),
        ({"lli": 8}, "lli"),
        ({"lli": -1}, "lli"),
        ({"lli": True}, "lli"),
    ],
)
def test_bad_carrier_fields_are_refused_naming_the_field(recording, change, field) -> None:
    epochs, environment = recording
    pipeline = GnssTightPipeline()
    state = pipeline.create(pipeline.resolve_options({"filter": "ukf", "seed": 1}), None)
    epoch = list(epochs[0])
    epoch[1] = dataclasses.replace(epoch[1], **change)
    with pytest.raises(PipelineInputError) as raised:
        pipeline.process(state, epoch, environment)
    assert [(p.index, p.field) for p in raised.value.problems] == [(1, field)]
