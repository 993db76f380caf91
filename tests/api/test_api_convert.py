"""The batch response is written from plain values, not the response models: it must be the very
bytes the models would write, for every kind of fix, and refuse non-finite numbers as they do."""

from __future__ import annotations

import dataclasses
import math

import pytest
from apihelp import epochs, scenario
from edgepos.api import convert
from edgepos.api.convert import fix_bytes, fix_to_json, fixes_bytes, joined_batch_body, to_json
from edgepos.api.schemas import BatchOut, FixEventOut, FixOut
from edgepos.api.streams import fix_event_data, fix_event_prefix
from edgepos.geo import GeodeticOrigin
from edgepos.pipelines.base import Fix, MeasurementUse, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline


def _fixes() -> list[Fix]:
    """Real rsu_imu fixes (initialised, tracking), a diverged one and an uninitialised one with null fields."""
    pipeline = get_pipeline("rsu_imu")
    environment = StaticEnvironment({rsu.id: rsu for rsu in scenario().rsus})
    state = pipeline.create(pipeline.resolve_options(None), None)
    observations = [o for epoch in epochs()[:6] for o in epoch]
    fixes, _ = pipeline.process(state, observations, environment)
    waiting = MeasurementUse(0, "gyro", False, "waiting for an RSU measurement to initialise")
    diverged = dataclasses.replace(
        fixes[-1],
        t=1.4,
        status="diverged",
        divergence="speed 3.4e+04 m/s exceeds max_speed_mps 150 m/s; reset",
    )
    foreign = MeasurementUse(1, "rsu", False, "RSU « Nord-Ost » außer Reichweite ✓")
    return [*fixes, diverged, Fix(t=1.5, status="uninitialised", measurements=[waiting, foreign])]


@pytest.mark.parametrize("include_state", [False, True])
@pytest.mark.parametrize("origin", [None, GeodeticOrigin(math.radians(48.1), math.radians(11.6), 520.0)])
def test_batch_body_is_what_the_response_models_write(
    include_state: bool, origin: GeodeticOrigin | None
) -> None:
    wire = [fix_to_json(fix, include_state, origin) for fix in _fixes()]
    models = [FixOut.model_validate(fix) for fix in wire]
    assert [model.model_dump(mode="json") for model in models] == wire  # same fields, same order
    written = [to_json(fix) for fix in wire]
    assert joined_batch_body(7, written) == BatchOut(seq=7, fixes=models).model_dump_json().encode()
    assert joined_batch_body(7, written) == to_json({"seq": 7, "fixes": wire})
    assert joined_batch_body(3, []) == to_json({"seq": 3, "fixes": []})


def test_a_fix_event_is_the_json_of_the_whole_event_around_the_fix_written_once() -> None:
    for fix in (fix_to_json(fix, False, None) for fix in _fixes()):
        event = fix_event_data(fix_event_prefix("s-1", 'car "7"', "rsu_imu", 12), to_json(fix))
        whole = {"session_id": "s-1", "vehicle_id": 'car "7"', "pipeline": "rsu_imu", "seq": 12, "fix": fix}
        assert event == to_json(whole)
        assert FixEventOut.model_validate_json(event).model_dump(mode="json") == whole


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_numbers_are_refused(value: float) -> None:
    fix = dataclasses.replace(_fixes()[-2], nis=value)
    with pytest.raises(ValueError, match="non-finite"):
        to_json(fix_to_json(fix, False, None))


def test_a_text_that_spells_nan_or_infinity_is_not_a_non_finite_number() -> None:
    fix = dataclasses.replace(_fixes()[-2], divergence="NaN or Infinity in the input; reset")
    assert b'"divergence":"NaN or Infinity in the input; reset"' in to_json(fix_to_json(fix, False, None))


@pytest.mark.parametrize("include_state", [False, True])
@pytest.mark.parametrize("origin", [None, GeodeticOrigin(math.radians(48.1), math.radians(11.6), 520.0)])
def test_a_fix_written_with_its_uses_written_once_is_the_same_bytes(
    include_state: bool, origin: GeodeticOrigin | None
) -> None:
    fixes = _fixes()
    for _ in range(2):  # the second time every use's JSON comes from the table
        for fix in fixes:
            assert fix_bytes(fix, include_state, origin) == to_json(fix_to_json(fix, include_state, origin))
    noisy = MeasurementUse(2, "pseudorange", True, None, True, None, True, None, 0.75, "C/N0 31 dB-Hz")
    changed = dataclasses.replace(fixes[-1], measurements=[noisy, *fixes[-1].measurements])
    assert fix_bytes(changed, False, None) == to_json(fix_to_json(changed, False, None))
    assert b'"noise_std":0.75' in fix_bytes(changed, False, None)


@pytest.mark.parametrize("include_state", [False, True])
@pytest.mark.parametrize("origin", [None, GeodeticOrigin(math.radians(48.1), math.radians(11.6), 520.0)])
def test_a_batch_of_fixes_written_at_once_is_each_fix_written_alone(
    include_state: bool, origin: GeodeticOrigin | None
) -> None:
    fixes = _fixes()
    alone = [fix_bytes(fix, include_state, origin) for fix in fixes]
    assert fixes_bytes(fixes, include_state, origin) == alone
    assert fixes_bytes(fixes[2:3], include_state, origin) == alone[2:3]
    assert fixes_bytes([], include_state, origin) == []


def test_fixes_whose_json_does_not_cut_one_per_fix_are_written_one_by_one(monkeypatch) -> None:
    """No field of a fix can hold '},{"t":' today (a string's quotes are escaped, no nested object has a "t"
    key); with a cut that comes more often than once between fixes, each fix is written alone."""
    fixes = _fixes()
    quoted = dataclasses.replace(fixes[1], divergence='"},{"t":1}')
    batch = [fixes[0], quoted, fixes[2]]
    assert fixes_bytes(batch, False, None) == [fix_bytes(fix, False, None) for fix in batch]
    monkeypatch.setattr(convert, "_NEXT_FIX", b",")
    monkeypatch.setattr(convert, "fix_bytes", lambda fix, *_: b"alone %d" % batch.index(fix))
    assert fixes_bytes(batch, False, None) == [b"alone 0", b"alone 1", b"alone 2"]


def test_the_use_table_keeps_what_it_keys_and_starts_afresh_when_full(monkeypatch) -> None:
    monkeypatch.setattr(convert, "_USE_BYTES", {})
    monkeypatch.setattr(convert, "_USE_BYTES_LIMIT", 3)
    uses = [MeasurementUse(i, "rsu", True) for i in range(5)]
    written = [convert._use_bytes(use) for use in uses]
    assert written == [to_json(convert._use_to_json(use)) for use in uses]
    assert len(convert._USE_BYTES) <= 3
    assert all(entry[0] is uses[key_index] for key_index, entry in _by_position(uses, convert._USE_BYTES))
    with pytest.raises(ValueError, match="non-finite"):
        convert._use_bytes(MeasurementUse(9, "pseudorange", True, noise_std=math.nan))


def _by_position(uses: list[MeasurementUse], table: dict) -> list[tuple[int, tuple]]:
    """The table's entries with the position in ``uses`` of the object their key names."""
    positions = {id(use): k for k, use in enumerate(uses)}
    return [(positions[key], entry) for key, entry in table.items()]
