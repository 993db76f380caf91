"""gnss_tight's integrity monitor (issue 21, solution-separation RAIM with the filter) on the real recording
(tests/data/gnss-rover, UKF, the first 60 epochs): a satellite ramp is detected and excluded, one not
excluded raises the alarm, the protection level survives the state's round trip, sessions stored before the
monitor get its defaults, and the monitor off leaves every fix unavailable."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from edgepos.core.observations import PseudorangeObservation
from edgepos.pipelines.base import Fix, StaticEnvironment
from edgepos.pipelines.gnss_integrity import EXCLUDED
from edgepos.pipelines.gnss_session import decode_session
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from gnssrecording import recording_epochs

EPOCHS = 60
RAMP_START = 20
RAMP_RATE = 3.0  # m/s on one satellite: a slowly growing reflection or clock fault
ONLY_RAIM = {"fault_probability": 0.0, "fde_probability": 0.0, "gate_probability": 0.0}
"""The pipeline's own screens off, so that what is excluded is the monitor's doing."""


@pytest.fixture(scope="module")
def recording() -> tuple[list[list[PseudorangeObservation]], StaticEnvironment]:
    return load()


def load() -> tuple[list[list[PseudorangeObservation]], StaticEnvironment]:
    """The first EPOCHS epochs of the recording (GPS, BeiDou, Galileo) and an environment with its ephemerides."""
    epochs, environment, _ = recording_epochs(EPOCHS, carrier=False)
    return epochs, environment


def _victim(epochs: list[list[PseudorangeObservation]]) -> tuple[str, int]:
    """A GPS satellite in every epoch."""
    common = set.intersection(*({(o.system, o.prn) for o in epoch if o.system == "G"} for epoch in epochs))
    return min(common)


def _ramped(epochs, victim, rate: float) -> list[list[PseudorangeObservation]]:
    out = []
    for k, epoch in enumerate(epochs):
        bias = rate * max(k - RAMP_START, 0)
        out.append(
            [
                dataclasses.replace(o, pseudorange=o.pseudorange + bias) if (o.system, o.prn) == victim else o
                for o in epoch
            ]
        )
    return out


def _run(epochs, environment, options) -> list[Fix]:
    pipeline = GnssTightPipeline()
    state = pipeline.create(pipeline.resolve_options({"filter": "ukf", "seed": 1, **options}), None)
    fixes = []
    for epoch in epochs:
        (fix,), state = pipeline.process(state, epoch, environment)
        fixes.append(fix)
    return fixes


def _excluded(fix: Fix) -> list[str]:
    return [
        use.reason for use in fix.measurements if use.reason is not None and use.reason.startswith(EXCLUDED)
    ]


def test_clean_epochs_carry_a_protection_level_and_no_exclusion(recording) -> None:
    fixes = _run(*recording, {})
    assert fixes[0].integrity == "unavailable" and fixes[0].protection_level is None  # initialisation
    tracked = fixes[5:]
    assert all(f.protection_level is not None and f.protection_level > 0.0 for f in tracked)
    assert not any(_excluded(f) for f in tracked)
    assert {f.integrity for f in tracked} <= {"ok", "alarm"}
    # at the default alert limit (5 m) every fix of this recording is in alarm (docs/integrity.md); a limit
    # above the protection levels leaves them ok
    relaxed = _run(*recording, {"alert_limit_m": 1000.0})
    assert all(f.integrity == "ok" for f in relaxed[5:])


def test_a_satellite_ramp_is_detected_and_excluded(recording) -> None:
    epochs, environment = recording
    victim = _victim(epochs)
    clean = _run(epochs, environment, {**ONLY_RAIM, "alert_limit_m": 1000.0})
    fixes = _run(_ramped(epochs, victim, RAMP_RATE), environment, {**ONLY_RAIM, "alert_limit_m": 1000.0})
    name = f"{victim[0]}{victim[1]:02d}"
    assert not any(_excluded(f) for f in fixes[:RAMP_START])
    detected = [k for k, f in enumerate(fixes) if any(name in reason for reason in _excluded(f))]
    assert detected, "the ramp was never excluded"
    first = detected[0]
    assert first - RAMP_START <= 15  # within 45 m of ramp
    assert detected == list(range(first, EPOCHS))  # and excluded every epoch after
    for f, c in zip(fixes, clean, strict=True):  # the excluded ramp moves the fix by little
        assert math.hypot(f.x - c.x, f.y - c.y) < 5.0
    # with the ramp out, the epochs test clean again (the one marginal E07 epoch of the clean run aside)
    assert sum(f.integrity != "ok" for f in fixes[first:]) <= 1


def test_a_fault_that_is_not_excluded_raises_the_alarm(recording) -> None:
    epochs, environment = recording
    victim = _victim(epochs)
    options = {**ONLY_RAIM, "alert_limit_m": 1000.0, "fault_exclusion": False}
    fixes = _run(_ramped(epochs, victim, RAMP_RATE), environment, options)
    assert all(f.integrity == "ok" for f in fixes[5:RAMP_START])
    assert not any(_excluded(f) for f in fixes)
    alarms = [k for k, f in enumerate(fixes) if f.integrity == "alarm"]
    assert alarms and alarms[0] - RAMP_START <= 15
    assert all(f.protection_level is not None for f in fixes[alarms[0] :])


def test_the_monitor_survives_the_state_round_trip_and_old_sessions_get_its_defaults(recording) -> None:
    epochs, environment = recording
    pipeline = GnssTightPipeline()
    options = pipeline.resolve_options({"filter": "ukf", "seed": 1})
    one_batch, _ = pipeline.process(
        pipeline.create(options, None), [o for epoch in epochs[:15] for o in epoch], environment
    )
    per_epoch = _run(epochs[:15], environment, {})
    assert [f.protection_level for f in one_batch] == [f.protection_level for f in per_epoch]
    assert [f.integrity for f in one_batch] == [f.integrity for f in per_epoch]
    # a session stored before the monitor existed: its options lack the monitor's, which get the defaults
    old = {k: v for k, v in options.items() if "integrity" not in k and "fault_prob" not in k}
    old["fault_probability"] = options["fault_probability"]
    state = pipeline.create(options, None)
    session = decode_session(state)
    session.options = {k: v for k, v in session.options.items() if k in old}
    fixes, _ = pipeline.process(session.to_bytes(), [o for epoch in epochs[:15] for o in epoch], environment)
    assert [f.protection_level for f in fixes] == [f.protection_level for f in per_epoch]


def test_the_monitor_off_leaves_fixes_unavailable(recording) -> None:
    epochs, environment = recording
    fixes = _run(epochs[:10], environment, {"integrity": False})
    assert {f.integrity for f in fixes} == {"unavailable"}
    assert {f.protection_level for f in fixes} == {None}
    on = _run(epochs[:10], environment, {})
    assert np.allclose([f.x for f in fixes], [f.x for f in on])  # no exclusion on clean epochs: same fixes
