"""Bodies validated in one pass from their bytes (``api/one_pass_body.py``): taken for valid batches, left
for every other body, and never accepting what FastAPI's own two-pass validation refuses."""

from __future__ import annotations

import hashlib
import json
import math
from typing import Any

import pytest
from apihelp import ADMIN, EVERY_MEASUREMENT, assert_error, batch_body, open_session, rsu_payload
from edgepos.api import one_pass_body
from edgepos.api.measurement_schemas import BatchIn
from edgepos.api.one_pass_body import OnePassBodyRoute, one_pass_model
from edgepos.api.routes import sessions
from edgepos.api.session_service import batch_hash
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import TypeAdapter, ValidationError

TWO_PASS = TypeAdapter(BatchIn)


def _two_pass(document: bytes) -> BatchIn:
    """What FastAPI does with a JSON body: the standard library's decoding, then the model's validation."""
    return TWO_PASS.validate_python(json.loads(document), from_attributes=True)


def test_the_batch_route_and_session_creation_take_their_model_in_one_pass() -> None:
    models = {
        (route.path, method): one_pass_model(route)
        for route in (*sessions.router.routes, *sessions.batch_router.routes)
        if isinstance(route, OnePassBodyRoute)
        for method in route.methods
    }
    assert models[("/v1/sessions/{session_id}/batches", "POST")] is BatchIn
    assert models[("/v1/sessions", "POST")] is not None
    assert models[("/v1/sessions/{session_id}", "GET")] is None  # no body: FastAPI's handler as is


def test_a_valid_batch_is_not_decoded_by_the_standard_library(client, monkeypatch) -> None:
    client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
    session_id, token = open_session(client)

    def refuse(*_args: Any, **_kwargs: Any) -> Any:
        raise AssertionError("a valid batch took the usual decoding")

    monkeypatch.setattr(one_pass_body, "usual_decoding", refuse)
    response = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 5), headers=token)
    assert response.status_code == 200, response.text
    assert len(response.json()["fixes"]) == 5


@pytest.mark.parametrize(
    ("content", "field"),
    [
        (b'{"seq": 1, "measurements": [{"type": "gyro", "t": "0", "yaw_rate": 0.0}]}', "measurements[0].t"),
        (b'{"seq": 1, "measurements": [', "body"),
        (b'\xef\xbb\xbf{"seq": 0, "measurements": [{"type": "gyro", "t": 0.0, "yaw_rate": 0.0}]}', "seq"),
    ],
)
def test_a_body_that_fails_in_one_pass_gets_fastapis_own_refusal(client, content, field) -> None:
    session_id, token = open_session(client)
    response = client.post(
        f"/v1/sessions/{session_id}/batches",
        content=content,
        headers={**token, "content-type": "application/json"},
    )
    error = assert_error(response, 422, "invalid_request")
    assert any(problem["field"].startswith(field) for problem in error["problems"]), error


_FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)
_NUMBER = st.one_of(_FINITE, st.integers(-(2**70), 2**70), st.sampled_from([math.inf, -math.inf, math.nan]))
_VALUE = st.one_of(
    _NUMBER, st.booleans(), st.none(), st.text(max_size=8), st.sampled_from(["S+000", "rsu-1"])
)


@st.composite
def _measurement(draw: st.DrawFn) -> dict[str, Any]:
    kind = draw(st.sampled_from(["rsu", "gyro", "odometer", "nonsense"]))
    fields = {"rsu": ["t", "rsu_id", "range", "bearing"], "gyro": ["t", "yaw_rate"]}.get(kind, ["t", "speed"])
    item: dict[str, Any] = {"type": kind}
    for name in fields:
        if draw(st.integers(0, 9)) > 0:  # now and then a field is missing
            item[name] = draw(_NUMBER) if name != "rsu_id" else draw(_VALUE)
    if draw(st.integers(0, 19)) == 0:
        item["extra"] = draw(_VALUE)
    return item


@st.composite
def _document(draw: st.DrawFn) -> bytes:
    body: dict[str, Any] = {
        "seq": draw(st.one_of(st.integers(-2, 2**64), _VALUE)),
        "measurements": draw(st.lists(_measurement(), max_size=4)),
    }
    if draw(st.booleans()):
        body["include_state"] = draw(_VALUE)
    return json.dumps(body).encode()  # NaN and Infinity as the standard library writes them


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_document())
def test_one_pass_accepts_only_what_two_passes_accept_and_builds_the_same_batch(document: bytes) -> None:
    try:
        one = BatchIn.model_validate_json(document)
    except ValidationError:
        return  # the route falls back to the two passes, whose answer stands
    two = _two_pass(document)  # must not raise: the one pass accepted it
    assert one == two
    for first, second in zip(one.measurements, two.measurements):
        for name, value in first:
            other = getattr(second, name)
            assert type(value) is type(other) and value == other, name  # (NaN is refused by both)


@given(st.lists(_FINITE, min_size=1, max_size=8))
def test_floats_come_out_bit_for_bit_as_the_standard_library_reads_them(values: list[float]) -> None:
    measurements = [{"type": "gyro", "t": 0.0, "yaw_rate": 0.0}] + [
        {
            "type": "rsu",
            "t": 0.0,
            "rsu_id": "S+000",
            "range": abs(v) % 1e6,
            "bearing": math.remainder(v, math.pi),
        }
        for v in values
    ]
    document = json.dumps({"seq": 1, "measurements": measurements}).encode()
    one, two = BatchIn.model_validate_json(document), _two_pass(document)
    for first, second in zip(one.measurements, two.measurements):
        assert first.model_dump() == second.model_dump()
        assert [math.copysign(1.0, v) for v in first.model_dump().values() if isinstance(v, float)] == [
            math.copysign(1.0, v) for v in second.model_dump().values() if isinstance(v, float)
        ]


@pytest.mark.parametrize("include_state", [False, True])
def test_the_batch_digest_hashes_the_same_bytes_as_the_models_json(include_state: bool) -> None:
    """Stored digests stay valid: the faster serialisation writes what model_dump_json() writes."""
    batch = BatchIn.model_validate(
        {"seq": 3, "measurements": EVERY_MEASUREMENT, "include_state": include_state}
    )
    assert {m.type for m in batch.measurements} == {m["type"] for m in EVERY_MEASUREMENT}
    assert batch_hash(batch) == hashlib.sha256(batch.model_dump_json().encode()).hexdigest()


_OPTIONAL = {
    "sat_position",
    "sat_clock",
    "doppler_hz",
    "carrier_cycles",
    "lli",
    "sat_velocity",
    "sat_clock_drift",
    "std",
    "distance",
    "speed",
}


@st.composite
def _valid_measurement(draw: st.DrawFn) -> dict[str, Any]:
    """One of EVERY_MEASUREMENT with its numbers redrawn (down to half, within the schema's bounds; -0.0; integers
    where floats go), its optional fields now and then null, and its keys in a random order."""
    item = dict(draw(st.sampled_from(EVERY_MEASUREMENT)))
    if item["type"] == "pseudorange" and draw(st.booleans()):
        item.update(sat_position=[2.0e7, -1.5e7, 0.5e7], sat_clock=1e-4)
    for name, value in list(item.items()):
        if isinstance(value, float) and draw(st.booleans()):
            item[name] = draw(
                st.one_of(
                    st.floats(0.5 * value, value) if value > 0 else st.floats(value, 0.5 * value),
                    st.just(round(value)) if round(value) == value else st.just(value),
                    st.just(-0.0) if value == 0.0 else st.just(value),
                )
            )
        if name in _OPTIONAL and name not in ("distance", "speed") and draw(st.integers(0, 3)) == 0:
            item[name] = None
    if item["type"] == "odometer" and draw(st.booleans()):
        item["distance" if "distance" not in item else "speed"] = None
    keys = draw(st.permutations(list(item)))
    return {key: item[key] for key in keys}


@settings(max_examples=200, deadline=None)
@given(st.lists(_valid_measurement(), min_size=1, max_size=12), st.booleans(), st.booleans())
def test_the_batch_digest_of_json_bodies_hashes_the_models_json(
    measurements: list[dict[str, Any]], include_state: bool, given_state: bool
) -> None:
    """The same on bodies validated from their bytes, as the route does: every measurement type, any
    order of keys, optional fields missing or null, integers in float fields, -0.0."""
    body: dict[str, Any] = {"measurements": measurements, "seq": 7}
    if given_state:
        body["include_state"] = include_state
    batch = BatchIn.model_validate_json(json.dumps(body))
    assert batch_hash(batch) == hashlib.sha256(batch.model_dump_json().encode()).hexdigest()


@pytest.mark.parametrize(
    "document",
    [
        b'{"vehicle_id": "car-1", "options": {"a": NaN}}',
        b'{"vehicle_id": "car-1", "options": {"a": 1e400, "b": 123456789012345678901234567890}}',
        b'{"vehicle_id": "car-1", "options": {"x": [1, 2.5, {"y": null}], "x": 3}}',
        b'{"vehicle_id": "car-1", "options": {"f": 0.1000000000000000055511151231257827, "g": -0.0}}',
        b'{"vehicle_id": "car-1", "options": {"s": "\\ud800"}}',
        b'{"vehicle_id": "car-1", "pipeline": "gnss_tight", "extra": 1}',
    ],
)
def test_session_creation_takes_free_form_options_in_one_pass_as_in_two(document: bytes) -> None:
    """The options are free JSON (dict[str, Any]): non-finite numbers, big integers, a repeated key and a lone
    surrogate come out of the one pass as the standard library reads them, or the one pass leaves them."""
    model = one_pass_model(
        next(r for r in sessions.router.routes if r.path == "/v1/sessions" and "POST" in r.methods)
    )
    assert model is not None
    try:
        one = model.model_validate_json(document)
    except ValidationError:
        return
    assert one == TypeAdapter(model).validate_python(json.loads(document), from_attributes=True)
