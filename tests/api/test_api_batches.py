"""The batch path: fixes per epoch, all-or-nothing validation, seq and idempotent replay, limits."""

from __future__ import annotations

import json
import math
import threading

import pytest
from apifakes import FailingPipeline, GatedPipeline, RsuOnlyPipeline
from apihelp import (
    ADMIN,
    NO_DOPPLER,
    assert_error,
    batch_body,
    make_settings,
    open_session,
    rsu_payload,
    wire,
)
from edgepos.api.app import create_app
from edgepos.geo import GeodeticOrigin
from edgepos.store import MemoryStore
from fastapi.testclient import TestClient


def _record(client, session_id):
    return client.portal.call(client.app.state.context.store.get, session_id)


def _post(client, session_id, body, headers):
    return client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=headers)


def _post_raw(client, session_id, content, headers):
    return client.post(
        f"/v1/sessions/{session_id}/batches",
        content=content,
        headers={**headers, "content-type": "application/json"},
    )


def test_one_fix_per_epoch_in_time_order(client):
    session_id, token = open_session(client)
    body = batch_body(1, 0, 10)
    response = _post(client, session_id, body, token)
    assert response.status_code == 200
    result = response.json()
    assert result["seq"] == 1
    fixes = result["fixes"]
    times = sorted({m["t"] for m in body["measurements"]})
    assert [f["t"] for f in fixes] == times
    assert fixes[0]["status"] == "initialised"
    assert {f["status"] for f in fixes[1:]} == {"tracking"}
    used = sorted(m["index"] for f in fixes for m in f["measurements"])
    assert used == list(range(len(body["measurements"])))
    for fix in fixes:
        assert fix["state"] is None and fix["latitude"] is None and fix["longitude"] is None
        assert math.isclose(fix["speed"], math.hypot(fix["vx"], fix["vy"]))
        assert len(fix["position_covariance"]) == 2
        assert sum(fix["model_probabilities"].values()) == pytest.approx(1.0)
    assert fixes[-1]["nis_dof"] > 0 and fixes[-1]["nis"] >= 0.0


def test_include_state_returns_the_full_state(client):
    session_id, token = open_session(client)
    fixes = _post(client, session_id, batch_body(1, 0, 3, include_state=True), token).json()["fixes"]
    state = fixes[-1]["state"]
    names = state["components"]
    assert names[:6] == ["xp", "xv", "xa", "yp", "yv", "ya"]  # the default bank shares these six
    assert len(state["mean"]) == len(names) and [len(row) for row in state["covariance"]] == [
        len(names)
    ] * len(names)
    assert (
        state["mean"][names.index("xp")] == fixes[-1]["x"]
        and state["mean"][names.index("yp")] == fixes[-1]["y"]
    )
    assert state["covariance"][0][0] == fixes[-1]["position_covariance"][0][0]


def test_uninitialised_epochs_have_null_kinematics(client):
    session_id, token = open_session(client)
    gyro_only = {"seq": 1, "measurements": [{"type": "gyro", "t": 0.5, "yaw_rate": 0.01}]}
    fix = _post(client, session_id, gyro_only, token).json()["fixes"][0]
    assert fix["status"] == "uninitialised"
    assert fix["x"] is None and fix["position_covariance"] is None
    assert fix["measurements"] == [
        {"index": 0, "type": "gyro", "used": False, "reason": fix["measurements"][0]["reason"], **NO_DOPPLER}
    ]


def test_retried_batch_is_applied_once(client):
    session_id, token = open_session(client)
    body = batch_body(1, 0, 5)
    first = _post(client, session_id, body, token)
    after_first = _record(client, session_id)
    # the same content again, serialised differently (key order, spacing): a retry after a lost reply
    reordered = {"measurements": body["measurements"], "seq": 1}
    again = _post_raw(client, session_id, json.dumps(reordered, indent=1), token)
    assert again.status_code == 200
    assert again.content == first.content
    assert _record(client, session_id) == after_first
    info = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    assert info["batches"] == 1 and info["epochs"] == 5 and info["last_seq"] == 1
    assert _post(client, session_id, batch_body(2, 5, 5), token).status_code == 200
    assert client.get(f"/v1/sessions/{session_id}", headers=token).json()["epochs"] == 10


@pytest.mark.parametrize(
    ("seq", "first_epoch", "reason_word"),
    [(2, 99, "different body"), (1, 0, "older"), (4, 5, "skips ahead")],
)
def test_seq_conflicts_are_409_and_change_nothing(client, seq, first_epoch, reason_word):
    session_id, token = open_session(client)
    assert _post(client, session_id, batch_body(1, 0, 3), token).status_code == 200
    assert _post(client, session_id, batch_body(2, 3, 3), token).status_code == 200
    before = _record(client, session_id)
    error = assert_error(_post(client, session_id, batch_body(seq, first_epoch, 2), token), 409, "conflict")
    assert reason_word in error["message"]
    assert error["problems"][0]["field"] == "seq"
    assert _record(client, session_id) == before


def test_first_batch_must_be_seq_1(client):
    session_id, token = open_session(client)
    assert_error(_post(client, session_id, batch_body(2, 0, 1), token), 409, "conflict")
    assert _record(client, session_id).last_seq == 0


def _bad_batches():
    good = [wire(o) for o in __import__("apihelp").batch_observations(10, 2)]
    return [
        (
            "unknown RSU",
            {"seq": 2, "measurements": [good[0], {**good[0], "rsu_id": "nowhere"}]},
            422,
            [(1, "measurements[1].rsu_id")],
        ),
        (
            "negative range",
            {"seq": 2, "measurements": [{**good[0], "range": -0.5}]},
            422,
            [(0, "measurements[0].range")],
        ),
        (
            "bearing beyond pi",
            {"seq": 2, "measurements": [{**good[0], "bearing": 3.2}]},
            422,
            [(0, "measurements[0].bearing")],
        ),
        (  # (older than the session's last epoch is no longer refused: tested below)
            "time far ahead of the rest of the batch",
            {"seq": 2, "measurements": [good[0], {**good[-1], "t": good[0]["t"] + 10.5}]},
            422,
            [(1, "measurements[1].t")],
        ),
        (  # the session's last epoch is t=0.5: t=-1.0 is too late for the 1 s lag window, but still checked
            "unknown RSU too late for the lag window",
            {"seq": 2, "measurements": [good[0], {**good[0], "t": -1.0, "rsu_id": "nowhere"}]},
            422,
            [(1, "measurements[1].rsu_id")],
        ),
        (
            "unknown type",
            {"seq": 2, "measurements": [{"type": "lidar", "t": 3.0}]},
            422,
            [(0, "measurements[0].type")],
        ),
        (
            "missing field",
            {"seq": 2, "measurements": [{"type": "gyro", "t": 3.0}]},
            422,
            [(0, "measurements[0].yaw_rate")],
        ),
        (
            "string number",
            {"seq": 2, "measurements": [{**good[0], "range": "5"}]},
            422,
            [(0, "measurements[0].range")],
        ),
        ("empty batch", {"seq": 2, "measurements": []}, 422, [(None, "measurements")]),
        ("seq zero", {"seq": 0, "measurements": good}, 422, [(None, "seq")]),
        ("unknown field", {"seq": 2, "measurements": good, "priority": 1}, 422, [(None, "priority")]),
    ]


@pytest.mark.parametrize(
    ("name", "body", "status", "expected"), _bad_batches(), ids=[c[0] for c in _bad_batches()]
)
def test_bad_batches_leave_the_session_untouched(client, name, body, status, expected):
    session_id, token = open_session(client)
    assert _post(client, session_id, batch_body(1, 0, 10), token).status_code == 200
    before = _record(client, session_id)
    error = assert_error(_post(client, session_id, body, token), status, "invalid_request")
    assert [(p["index"], p["field"]) for p in error["problems"]] == expected
    assert _record(client, session_id) == before


def test_late_measurements_are_filtered_at_their_time_and_too_late_ones_reported(client):
    """The lag window (max_delay_s 1 s by default): a gyro reading between two epochs already answered is
    inserted at its time and the later fix comes back revised; one older than the window is not used, says
    why in the newest fix, and the rest of the batch is applied."""
    session_id, token = open_session(client)
    first = _post(client, session_id, batch_body(1, 0, 10), token).json()["fixes"]
    assert first[-1]["t"] == 0.5
    new_epoch = batch_body(2, 10, 1)["measurements"]
    late = {"type": "gyro", "t": 0.475, "yaw_rate": 0.0}
    too_late = {"type": "gyro", "t": -0.75, "yaw_rate": 0.0}
    body = {"seq": 2, "measurements": [too_late, *new_epoch, late]}
    response = _post(client, session_id, body, token)
    assert response.status_code == 200, response.text
    fixes = response.json()["fixes"]
    assert [(f["t"], f["revised"]) for f in fixes] == [
        (0.475, False),
        (0.5, True),
        (new_epoch[0]["t"], False),
    ]
    assert fixes[0]["measurements"] == [
        {"index": len(body["measurements"]) - 1, "type": "gyro", "used": True, "reason": None, **NO_DOPPLER}
    ]
    assert fixes[1]["measurements"] == []  # a revised fix lists only the batch's measurements of its epoch
    assert fixes[1]["x"] != first[-1]["x"]
    newest = {u["index"]: u for u in fixes[-1]["measurements"]}
    assert sorted(newest) == list(range(len(new_epoch) + 1))
    assert not newest[0]["used"] and newest[0]["reason"].startswith("too late: t=-0.75 is ")
    assert "max_delay_s 1 s" in newest[0]["reason"]
    assert all(newest[i]["used"] for i in range(1, len(new_epoch) + 1))
    info = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    # revised fixes are not new epochs; the late reading's is
    assert (info["last_seq"], info["batches"], info["epochs"], info["t"]) == (2, 2, 12, new_epoch[0]["t"])
    assert info["last_fix"] == {**fixes[-1], "state": None}


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_literals_are_refused(client, literal):
    session_id, token = open_session(client)
    before = _record(client, session_id)
    content = (
        '{"seq": 1, "measurements": [{"type": "gyro", "t": 1.0, "yaw_rate": 0.1},'
        ' {"type": "rsu", "t": '
        + literal
        + ', "rsu_id": "S+000", "range": '
        + literal
        + ', "bearing": 0.0}]}'
    )
    error = assert_error(_post_raw(client, session_id, content, token), 422, "invalid_request")
    assert [(p["index"], p["field"]) for p in error["problems"]] == [
        (1, "measurements[1].t"),
        (1, "measurements[1].range"),
    ]
    assert _record(client, session_id) == before


def test_every_problem_of_a_batch_is_listed(client):
    session_id, token = open_session(client)
    good = batch_body(1, 0, 1)["measurements"]
    bad = [{**good[0], "rsu_id": "x1"}, good[-1], {**good[0], "rsu_id": "x2"}]
    error = assert_error(
        _post(client, session_id, {"seq": 1, "measurements": bad}, token), 422, "invalid_request"
    )
    assert [(p["index"], p["field"]) for p in error["problems"]] == [
        (0, "measurements[0].rsu_id"),
        (2, "measurements[2].rsu_id"),
    ]


def test_invalid_json_is_422(client):
    session_id, token = open_session(client)
    error = assert_error(
        _post_raw(client, session_id, '{"seq": 1, "measurements": [', token), 422, "invalid_request"
    )
    assert error["problems"][0]["field"].startswith("body") or error["problems"][0]["index"] is None


def test_batch_size_limit_is_422(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, max_batch_measurements=4))) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        body = batch_body(1, 0, 3)
        assert len(body["measurements"]) > 4
        error = assert_error(_post(client, session_id, body, token), 422, "invalid_request")
        assert (
            error["problems"][0]["field"] == "measurements" and "at most 4" in error["problems"][0]["reason"]
        )
        assert _record(client, session_id).last_seq == 0


def test_body_size_limit_is_413_before_parsing(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, max_body_bytes=2048))) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        content = json.dumps(batch_body(1, 0, 20))
        assert len(content) > 2048
        error = assert_error(_post_raw(client, session_id, content, token), 413, "payload_too_large")
        assert "2048" in error["message"]
        # streamed without Content-Length: counted while reading
        chunks = (content[i : i + 500].encode() for i in range(0, len(content), 500))
        response = client.post(
            f"/v1/sessions/{session_id}/batches",
            content=chunks,
            headers={**token, "content-type": "application/json"},
        )
        assert_error(response, 413, "payload_too_large")
        # not even valid JSON: refused for its size, never parsed
        assert_error(_post_raw(client, session_id, "x" * 5000, token), 413, "payload_too_large")
        assert _record(client, session_id).last_seq == 0
        small = batch_body(1, 0, 1)
        assert _post(client, session_id, small, token).status_code == 200


def test_estimation_failure_is_422_and_changes_nothing(tmp_path):
    app = create_app(make_settings(tmp_path), pipelines={"rsu_imu": FailingPipeline()})
    with TestClient(app) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        before = _record(client, session_id)
        error = assert_error(_post(client, session_id, batch_body(1, 0, 2), token), 422, "estimation_failed")
        assert "not positive definite" in error["message"]
        assert _record(client, session_id) == before


def test_measurements_the_pipeline_does_not_use_are_refused(tmp_path):
    with TestClient(create_app(make_settings(tmp_path), pipelines={"rsu_imu": RsuOnlyPipeline()})) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        body = batch_body(1, 0, 1)
        error = assert_error(_post(client, session_id, body, token), 422, "invalid_request")
        gyro_index = len(body["measurements"]) - 1
        assert [(p["index"], p["field"]) for p in error["problems"]] == [
            (gyro_index, f"measurements[{gyro_index}].type")
        ]


def test_fixes_carry_latitude_longitude_with_an_origin(tmp_path):
    settings = make_settings(tmp_path, origin_lat=48.1375, origin_lon=11.575, origin_height=520.0)
    with TestClient(create_app(settings)) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        fixes = _post(client, session_id, batch_body(1, 0, 4), token).json()["fixes"]
    origin = GeodeticOrigin.from_degrees(48.1375, 11.575, 520.0)
    for fix in fixes:
        latitude, longitude, _ = origin.enu_to_geodetic(fix["x"], fix["y"], 0.0)
        assert (fix["latitude"], fix["longitude"]) == (latitude, longitude)
        assert abs(fix["latitude"] - math.radians(48.1375)) < 1e-4


def test_requests_for_one_session_never_interleave(tmp_path):
    pipeline = GatedPipeline()
    # The filter thread's lane: a gated pipeline on the loop lane would hold the very loop that must
    # bring the second request to the session's lock (the lock is the same whichever lane filters).
    settings = make_settings(tmp_path, light_lane="thread")
    with TestClient(create_app(settings, pipelines={"rsu_imu": pipeline})) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        # The gate opens only once the second request waits on the session's lock: opened any earlier
        # (the second thread not scheduled yet, as on a busy machine), the two requests would not
        # overlap at all and the test would prove nothing.
        store = client.app.state.context.store
        hold = store.session_lock
        arrived: list[str] = []
        second_waits = threading.Event()

        def observed_lock(locked_id: str):
            arrived.append(locked_id)
            if len(arrived) == 2:
                second_waits.set()
            return hold(locked_id)

        store.session_lock = observed_lock
        pipeline.gate = threading.Event()
        body = batch_body(1, 0, 5)
        responses = []
        threads = [
            threading.Thread(target=lambda: responses.append(_post(client, session_id, body, token)))
            for _ in range(2)
        ]
        threads[0].start()
        assert pipeline.entered.wait(10.0)
        threads[1].start()
        assert second_waits.wait(10.0), "the second request never reached the session lock"
        # while the first is inside the filter, the event loop still serves other requests
        assert client.get("/healthz").status_code == 200
        assert client.get(f"/v1/sessions/{session_id}", headers=token).json()["last_seq"] == 0
        pipeline.gate.set()
        for thread in threads:
            thread.join(20.0)
    assert not pipeline.timed_out
    assert len(pipeline.calls) == 1  # the second request waited, then found the batch applied: a replay
    assert arrived == [session_id, session_id]  # each took the lock once: no lost compare-and-set either
    assert [r.status_code for r in responses] == [200, 200]
    assert responses[0].content == responses[1].content


class RacingStore(MemoryStore):
    """On its first compare-and-set, another worker's identical write lands first."""

    def __init__(self, ttl_s: float) -> None:
        super().__init__(ttl_s)
        self.raced = False

    async def compare_and_set(self, record, expected_version):
        if not self.raced and record.last_seq > 0:
            self.raced = True
            assert await super().compare_and_set(record, expected_version)
            return False
        return await super().compare_and_set(record, expected_version)


def test_lost_compare_and_set_reloads_and_replays(tmp_path):
    settings = make_settings(tmp_path)
    store = RacingStore(settings.session_ttl_s)
    with TestClient(create_app(settings, store=store)) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        response = _post(client, session_id, batch_body(1, 0, 3), token)
        assert response.status_code == 200 and store.raced
        record = _record(client, session_id)
        assert record.last_response == response.content and record.batches == 1 and record.version == 1
        metrics = client.get("/metrics").text
    assert "edgepos_store_conflicts_total 1.0" in metrics
    assert 'edgepos_batches_total{outcome="replayed"} 1.0' in metrics


@pytest.mark.parametrize("damage", ["truncated", "foreign"])
def test_a_stored_state_this_server_cannot_read_is_a_409_not_a_500(client, damage):
    """After an upgrade that changed a pipeline's state layout (or a damaged record), the vehicle is
    told to start over; the record is left as it was."""
    import dataclasses

    from edgepos.pipelines.registry import get_pipeline

    session_id, token = open_session(client)
    assert _post(client, session_id, batch_body(1, 0, 2), token).status_code == 200
    store = client.app.state.context.store
    record = _record(client, session_id)
    if damage == "truncated":
        unreadable = record.state[: len(record.state) // 2]
    else:  # a well-formed state of another pipeline under this session's name
        unreadable = get_pipeline("v2v_coop").create(get_pipeline("v2v_coop").resolve_options({}), None)
    damaged_record = dataclasses.replace(record, state=unreadable)
    assert client.portal.call(store.compare_and_set, damaged_record, record.version)
    damaged = _record(client, session_id)

    for response in (
        client.get(f"/v1/sessions/{session_id}", headers=token),
        _post(client, session_id, batch_body(2, 2, 2), token),
    ):
        error = assert_error(response, 409, "conflict")
        assert "open a new one" in error["message"]
    assert _record(client, session_id) == damaged
    assert client.delete(f"/v1/sessions/{session_id}", headers=token).status_code == 204


@pytest.mark.parametrize(
    "content_type",
    [
        None,
        "text/plain",
        "application/x-www-form-urlencoded",
        "application/json; charset=utf-16",
        "multipart/form-data",
    ],
)
def test_a_body_that_is_not_declared_json_is_415_and_changes_nothing(client, content_type):
    session_id, token = open_session(client)
    content = json.dumps(batch_body(1, 0, 2))
    headers = {**token, **({"content-type": content_type} if content_type else {})}
    if content_type and "utf-16" in content_type:
        content = content.encode("utf-16")
    response = client.post(f"/v1/sessions/{session_id}/batches", content=content, headers=headers)
    error = assert_error(response, 415, "unsupported_media_type")
    assert error["problems"][0]["field"] == "Content-Type"
    assert client.get(f"/v1/sessions/{session_id}", headers=ADMIN).json()["last_seq"] == 0
    plain_json = {**token, "content-type": "application/json; charset=UTF-8"}
    assert (
        client.post(
            f"/v1/sessions/{session_id}/batches", content=json.dumps(batch_body(1, 0, 2)), headers=plain_json
        ).status_code
        == 200
    )


def test_a_json_syntax_error_names_line_and_column(client):
    session_id, token = open_session(client)
    content = '{\n  "seq": 1,\n  "measurements": [\n    {"type": "gyro" "t": 0.1}\n  ]\n}'
    error = assert_error(_post_raw(client, session_id, content, token), 422, "invalid_request")
    [problem] = error["problems"]
    assert problem["field"] == "body"
    assert "line 4, column 21" in problem["reason"], problem["reason"]


def _count_reads(client, monkeypatch) -> list[str]:
    store = client.app.state.context.store
    reads: list[str] = []
    real_get = store.get

    async def counted(session_id, *, with_response=True):
        reads.append(session_id if with_response else f"{session_id} without its stored answer")
        return await real_get(session_id, with_response=with_response)

    monkeypatch.setattr(store, "get", counted)
    return reads


def test_a_batch_with_a_session_token_reads_the_session_once(client, monkeypatch):
    session_id, token = open_session(client)
    reads = _count_reads(client, monkeypatch)
    assert _post(client, session_id, batch_body(1, 0, 3), token).status_code == 200
    # the token check's read is the one the batch is applied on, and it need not carry the stored answer
    assert reads == [f"{session_id} without its stored answer"]
    reads.clear()
    assert _post(client, session_id, batch_body(1, 0, 3), token).status_code == 200  # a replay
    # a replay or a refusal is decided on a fresh read, with the answer to give back
    assert reads == [f"{session_id} without its stored answer", session_id]


def test_a_stale_prefetched_record_never_decides_a_batch(client):
    """The record the token check read may be old by the time the batch is applied (another request
    of the vehicle got in between): the next seq is checked again by the compare-and-set, anything
    else on a fresh read."""
    from edgepos.api import session_service
    from edgepos.api.measurement_schemas import BatchIn

    session_id, token = open_session(client)
    context = client.app.state.context
    stale = _record(client, session_id)
    first = _post(client, session_id, batch_body(1, 0, 3), token)
    assert first.status_code == 200
    # the same seq 1 again on the stale record (which says seq 1 is next): the compare-and-set fails, the
    # fresh read finds it applied with this body, and the stored answer comes back
    again = BatchIn.model_validate(batch_body(1, 0, 3))
    replayed = client.portal.call(session_service.apply_batch, context, session_id, again, stale)
    assert json.loads(replayed) == first.json()
    # seq 2 on the stale record (which says seq 1 is next) is not refused as skipping ahead: it is decided
    # on a fresh read and applied
    second = BatchIn.model_validate(batch_body(2, 3, 3))
    applied = json.loads(client.portal.call(session_service.apply_batch, context, session_id, second, stale))
    assert applied["seq"] == 2 and _record(client, session_id).last_seq == 2
