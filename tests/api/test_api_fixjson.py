"""``convert.fixes_bytes`` writes a batch's fixes through a serializer of the Fix dataclass and joins each
fix's uses once per sequence of use objects: the bytes must be the reference's, ``to_json(fix_to_json(...))``
per fix, for any fix the types allow and for the fixes the pipelines serve, and non-finite numbers are
refused as the reference refuses them."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import pytest
from apihelp import batch_body, open_session
from edgepos.api import convert, session_service
from edgepos.api.convert import fix_to_json, fixes_bytes, to_json
from edgepos.geo import GeodeticOrigin
from edgepos.pipelines.base import Fix, MeasurementUse
from gnsswire import quick_fixes, upload_ephemerides
from hypothesis import given, settings
from hypothesis import strategies as st

ORIGIN = GeodeticOrigin(math.radians(48.1), math.radians(11.6), 520.0)

_SPECIAL = [0.0, -0.0, 1.0, -3.0, 1e-300, -1e-300, 5e-324, 1e300, -1e300, 1e16, 1e-5, 123456789.0, 0.1]
_floats = st.floats(allow_nan=False, allow_infinity=False) | st.sampled_from(_SPECIAL)
_text = st.text(max_size=12) | st.sampled_from(
    ["tracking", "ok", 'a,"b"', '},{"t":', "ü ✓ %b %s", "NaN", ":NaN"]
)
_number = _floats | st.integers(-(2**53), 2**53)
# x and y within a site (a site origin turns them into a latitude and longitude; far out the geodesy
# overflows)
_site = st.floats(-1e5, 1e5) | st.sampled_from([0.0, -0.0, 1e-300, 2.0]) | st.integers(-1000, 1000)


def _maybe(strategy: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    return st.none() | strategy


def _matrix(size: int) -> st.SearchStrategy[list[list[float]]]:
    return st.lists(st.lists(_floats, min_size=size, max_size=size), min_size=size, max_size=size)


_uses = st.builds(
    MeasurementUse,
    index=st.integers(0, 500),
    kind=_text,
    used=st.booleans(),
    reason=_maybe(_text),
    doppler_used=_maybe(st.booleans()),
    doppler_reason=_maybe(_text),
    correction_applied=_maybe(st.booleans()),
    correction_reason=_maybe(_text),
    noise_std=_maybe(_floats),
    noise_reason=_maybe(_text),
)


@st.composite
def _fix(draw: st.DrawFn) -> Fix:
    size = draw(st.integers(0, 4))
    return Fix(
        t=draw(_number),
        status=draw(_text),
        x=draw(_maybe(_site)),
        y=draw(_maybe(_site)),
        vx=draw(_maybe(_floats)),
        vy=draw(_maybe(_floats)),
        speed=draw(_maybe(_floats)),
        heading=draw(_maybe(_floats)),
        yaw_rate=draw(_maybe(_floats)),
        position_cov=draw(_maybe(_matrix(2) | _matrix(draw(st.integers(0, 3))))),
        state_components=tuple(draw(st.lists(_text, min_size=size, max_size=size))),
        state=draw(_maybe(st.lists(_floats, min_size=size, max_size=size))),
        state_cov=draw(_maybe(_matrix(size))),
        model_probabilities=draw(st.dictionaries(_text, _floats, max_size=4)),
        nis=draw(_maybe(_floats)),
        nis_dof=draw(st.integers(0, 40)),
        measurements=draw(st.lists(_uses, max_size=4)),
        latitude=draw(_maybe(_floats)),
        longitude=draw(_maybe(_floats)),
        height=draw(_maybe(_floats)),
        revised=draw(st.booleans()),
        constraints=draw(_maybe(st.tuples() | st.lists(_text, max_size=3).map(tuple))),
        divergence=draw(_maybe(_text)),
        protection_level=draw(_maybe(_floats)),
        integrity=draw(_text),
    )


def _reference(fixes: list[Fix], include_state: bool, origin: GeodeticOrigin | None) -> list[bytes]:
    return [to_json(fix_to_json(fix, include_state, origin)) for fix in fixes]


@settings(max_examples=300, deadline=None)
@given(
    fixes=st.lists(_fix(), max_size=5), include_state=st.booleans(), origin=st.sampled_from([None, ORIGIN])
)
def test_any_batch_of_fixes_is_written_as_the_reference_writes_each_fix(
    fixes: list[Fix], include_state: bool, origin: GeodeticOrigin | None
) -> None:
    try:
        expected = _reference(fixes, include_state, origin)
    except ValueError:  # text that spells a non-finite number where the check reads one: refused both ways
        with pytest.raises(ValueError, match="non-finite"):
            fixes_bytes(fixes, include_state, origin)
        return
    assert fixes_bytes(fixes, include_state, origin) == expected
    assert fixes_bytes(fixes, include_state, origin) == expected  # the uses' table's entries, the same


@settings(max_examples=100, deadline=None)
@given(
    fixes=st.lists(_fix(), min_size=1, max_size=4),
    which=st.integers(0, 3),
    field=st.sampled_from(
        ["t", "x", "speed", "nis", "protection_level", "probability", "covariance", "state"]
    ),
    value=st.sampled_from([math.nan, math.inf, -math.inf]),
    include_state=st.booleans(),
)
def test_a_non_finite_number_anywhere_is_refused(
    fixes: list[Fix], which: int, field: str, value: float, include_state: bool
) -> None:
    fix = fixes[which % len(fixes)]
    if field == "probability":
        fix.model_probabilities["ca"] = value
    elif field == "covariance":
        object.__setattr__(fix, "position_cov", [[1.0, value], [value, 1.0]])
    elif field == "state":
        object.__setattr__(fix, "state", [value])
        object.__setattr__(fix, "state_components", ("x",))
        object.__setattr__(fix, "state_cov", [[1.0]])
    else:
        object.__setattr__(fix, field, value)
    written = field != "state" or include_state
    if written:
        with pytest.raises(ValueError, match="non-finite"):
            _reference(fixes, include_state, None)
        with pytest.raises(ValueError, match="non-finite"):
            fixes_bytes(fixes, include_state, None)


def test_a_fixs_uses_are_joined_once_per_sequence_of_use_objects(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(convert, "_USES_BYTES", {})
    monkeypatch.setattr(convert, "_USES_BYTES_LIMIT", 2)
    shared = [MeasurementUse(i, "rsu", True) for i in range(3)]
    fixes = [Fix(t=float(k), status="tracking", measurements=shared[k:]) for k in range(3)]
    assert fixes_bytes(fixes, False, None) == _reference(fixes, False, None)
    assert len(convert._USES_BYTES) <= 2
    for key, (uses, _) in convert._USES_BYTES.items():
        assert key == tuple(map(id, uses))
    fixes[0].measurements[0] = MeasurementUse(0, "gyro", False, "late")  # a new object: a new key
    assert fixes_bytes(fixes, False, None) == _reference(fixes, False, None)


@pytest.fixture
def checked(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[tuple[Fix, bool]]]:
    """The service's ``fixes_bytes`` compared with the reference on every batch it answers; yields the
    fixes it wrote, with include_state."""
    seen: list[tuple[Fix, bool]] = []

    def checking(fixes: list[Fix], include_state: bool, origin: GeodeticOrigin | None) -> list[bytes]:
        written = fixes_bytes(fixes, include_state, origin)
        assert written == _reference(list(fixes), include_state, origin)
        seen.extend((fix, include_state) for fix in fixes)
        return written

    monkeypatch.setattr(session_service, "fixes_bytes", checking)
    yield seen


@pytest.mark.parametrize("include_state", [False, True])
@pytest.mark.parametrize("integrity", [False, True])
def test_the_rsu_imu_answers_are_the_reference_bytes(
    client: Any, checked: list[tuple[Fix, bool]], include_state: bool, integrity: bool
) -> None:
    options = {"integrity": integrity}
    session_id, token = open_session(client, pipeline="rsu_imu", vehicle_id="v-fixjson", options=options)
    for seq, (first, count) in enumerate([(0, 1), (1, 20), (21, 20)], start=1):
        body = batch_body(seq, first, count, include_state=include_state)
        response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token)
        assert response.status_code == 200, response.text
    assert len(checked) >= 41
    assert any(fix.state is not None for fix, state in checked if state) == include_state
    assert any(fix.integrity != "unavailable" for fix, _ in checked) == integrity


def test_the_gnss_tight_answers_are_the_reference_bytes(client: Any, checked: list[tuple[Fix, bool]]) -> None:
    upload_ephemerides(client)
    fixes = quick_fixes(client, "v-fixjson-gnss", {})
    assert fixes
    assert any(fix.latitude is not None and fix.constraints is not None for fix, _ in checked)
