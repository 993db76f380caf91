"""A hypothesis state machine drives the API beside an in-process reference pipeline.

Rules open sessions (various filters, with or without a known start), send the next epochs of the
paper scenario's measurements, send late measurements (inside the lag window: filtered at their time,
earlier fixes revised; beyond it: reported unused), retry the last batch, send every kind of bad request
(malformed JSON, wrong types, huge numbers, NaN, unicode ids, unknown RSUs, too-late measurements of
an unknown RSU, a clock jump within the batch, seq gaps and reuse, over-long and over-size batches)
and delete sessions. Opening a session for a vehicle that has
one supersedes the old one, whose token then gets 409 superseded. After every step, for every session:
the served fixes were the reference's bit for bit, refused requests got a 4xx with the standard
error body and changed nothing, and the stored counters and latest fix equal the model's.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from apihelp import ADMIN, ADMIN_KEY, bearer, epochs, rsu_payload, scenario, wire
from edgepos.api.app import create_app
from edgepos.api.convert import fix_to_json
from edgepos.api.schemas import FixOut
from edgepos.api.settings import Settings
from edgepos.core.errors import EstimationError
from edgepos.pipelines import lag
from edgepos.pipelines.base import InitialState, PipelineInputError, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, event, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    Bundle,
    RuleBasedStateMachine,
    consumes,
    initialize,
    invariant,
    precondition,
    rule,
)

MAX_MEASUREMENTS = 40
MAX_BODY = 16 * 1024
PIPELINE = get_pipeline("rsu_imu")
ENVIRONMENT = StaticEnvironment({rsu.id: rsu for rsu in scenario().rsus})
EPOCHS = epochs(11)
START = {"x": 0.0, "y": 0.0, "vx": 10.0, "vy": 0.0, "position_std": 1.0, "velocity_std": 1.0}


def _app_client() -> TestClient:
    test_settings = Settings(
        admin_key=ADMIN_KEY,
        admin_key_file=Path("/nonexistent/never-written.key"),
        rate_limit_per_s=0,
        max_batch_measurements=MAX_MEASUREMENTS,
        max_body_bytes=MAX_BODY,
    )
    client = TestClient(create_app(test_settings))
    assert client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
    return client


CLIENT = _app_client()


@dataclass
class Model:
    """What the reference says one session holds."""

    session_id: str
    token: str
    vehicle_id: str
    state: bytes
    last_seq: int = 0
    epochs: int = 0
    next_epoch: int = 0
    last_fix: dict[str, Any] | None = None
    last_body: dict[str, Any] | None = None
    last_response: bytes | None = None
    deleted: bool = field(default=False)
    superseded_by: str | None = None

    @property
    def live(self) -> bool:
        return not self.deleted and self.superseded_by is None


def _wire_fix(fix: Any) -> dict[str, Any]:
    return json.loads(FixOut.model_validate(fix_to_json(fix, False, None)).model_dump_json())


def _measurements(first: int, count: int) -> list[dict[str, Any]]:
    return [wire(o) for epoch in EPOCHS[first : first + count] for o in epoch]


BAD_KINDS = [
    "not_json",
    "truncated_json",
    "wrong_type",
    "huge_number",
    "nan_literal",
    "unicode_rsu",
    "unknown_rsu",
    "negative_range",
    "too_late_unknown_rsu",
    "clock_jump_in_batch",
    "seq_gap",
    "seq_zero",
    "seq_reused_other_body",
    "too_many",
    "too_large",
    "empty",
    "unknown_type",
    "array_body",
    "bool_for_int",
]


class ApiBesideReference(RuleBasedStateMachine):
    sessions = Bundle("sessions")

    def __init__(self) -> None:
        super().__init__()
        self.models: list[Model] = []

    @initialize(target=sessions)
    def first_session(self) -> Model:
        return self.open_session("ckf", True, "car-0")

    @precondition(lambda self: len(self.models) < 3)
    @rule(
        target=sessions,
        filter_name=st.sampled_from(["ckf", "ukf", "ekf"]),
        known_start=st.booleans(),
        vehicle=st.one_of(
            st.just("car-1"), st.text(st.characters(categories=["L", "N", "P", "S"]), min_size=1, max_size=20)
        ),
    )
    def open_session(self, filter_name: str, known_start: bool, vehicle: str) -> Model:
        body: dict[str, Any] = {"vehicle_id": vehicle, "options": {"filter": filter_name}}
        if known_start:
            body["initial_state"] = START
        response = CLIENT.post("/v1/sessions", json=body, headers=ADMIN)
        if response.status_code == 422:  # a vehicle id the schema refuses (e.g. control characters)
            assert response.json()["error"]["problems"][0]["field"] == "vehicle_id"
            body["vehicle_id"] = "car"
            response = CLIENT.post("/v1/sessions", json=body, headers=ADMIN)
        assert response.status_code == 201, response.text
        created = response.json()
        initial = InitialState(**START) if known_start else None
        state = PIPELINE.create(PIPELINE.resolve_options({"filter": filter_name}), initial)
        model = Model(created["session_id"], created["token"], body["vehicle_id"], state)
        replaced = [old for old in self.models if old.live and old.vehicle_id == model.vehicle_id]
        assert created["superseded"] == (replaced[0].session_id if replaced else None)
        for old in replaced:
            old.superseded_by = model.session_id
        self.models.append(model)
        return model

    def _assert_superseded(self, model: Model, response: Any) -> None:
        assert response.status_code == 409, response.text
        error = response.json()["error"]
        assert error["code"] == "superseded" and model.superseded_by in error["message"]

    def _post(self, model: Model, content: bytes | str, token: str | None = None) -> Any:
        return CLIENT.post(
            f"/v1/sessions/{model.session_id}/batches",
            content=content,
            headers={**bearer(token or model.token), "Content-Type": "application/json"},
        )

    @rule(model=sessions, count=st.integers(1, 6))
    def send_next_epochs(self, model: Model, count: int) -> None:
        if model.deleted or model.next_epoch + count > len(EPOCHS):
            return
        body = {"seq": model.last_seq + 1, "measurements": _measurements(model.next_epoch, count)}
        if model.superseded_by is not None:
            self._assert_superseded(model, self._post(model, json.dumps(body)))
            return
        observations = [o for epoch in EPOCHS[model.next_epoch : model.next_epoch + count] for o in epoch]
        fixes, state = PIPELINE.process(model.state, observations, ENVIRONMENT)
        response = self._post(model, json.dumps(body))
        assert response.status_code == 200, response.text
        served = response.json()
        assert served["seq"] == body["seq"]
        assert served["fixes"] == [_wire_fix(fix) for fix in fixes]  # floats compared exactly
        model.state, model.last_seq = state, body["seq"]
        model.epochs += len(fixes)
        model.next_epoch += count
        model.last_fix = served["fixes"][-1]
        model.last_body, model.last_response = body, response.content

    @rule(
        model=sessions,
        # seconds before the session's newest epoch: the same epoch, between earlier epochs (0.05 s apart),
        # before the first one, and beyond the window (max_delay_s 1 s)
        lateness=st.sampled_from([0.0, 0.0125, 0.3125, 0.9875, 1.5, 30.0]),
        which=st.sampled_from(["all", "gyro", "rsu"]),
    )
    def send_late_measurements(self, model: Model, lateness: float, which: str) -> None:
        """The next epoch's measurements (or some), dated ``lateness`` before the newest epoch: the served
        fixes (new and revised) are the reference's bit for bit, and the counters follow (a revised fix is
        not a new epoch)."""
        if model.deleted or model.epochs == 0:
            return
        t = model.last_fix["t"] - lateness
        source = EPOCHS[min(model.next_epoch, len(EPOCHS) - 1)]
        observations = [dataclasses.replace(o, t=t) for o in source if which in ("all", o.kind)]
        body = {"seq": model.last_seq + 1, "measurements": [wire(o) for o in observations]}
        if model.superseded_by is not None:
            self._assert_superseded(model, self._post(model, json.dumps(body)))
            return
        try:
            fixes, state = PIPELINE.process(model.state, observations, ENVIRONMENT)
        except (PipelineInputError, EstimationError):
            event("late measurements: refused")
            response = self._post(model, json.dumps(body))
            assert response.status_code == 422, response.text
            return
        response = self._post(model, json.dumps(body))
        assert response.status_code == 200, response.text
        served = response.json()
        event(f"late measurements: {len(served['fixes'])} fixes, {sum(not f.revised for f in fixes)} new")
        assert served["fixes"] == [_wire_fix(fix) for fix in fixes]  # floats compared exactly
        assert served["fixes"][-1]["t"] == model.last_fix["t"]  # nothing newer came
        uses = [u for f in served["fixes"] for u in f["measurements"]]
        assert sorted(u["index"] for u in uses) == list(range(len(observations)))
        if lateness > lag.DEFAULTS["max_delay_s"]:
            assert not any(u["used"] for u in uses) and all(
                u["reason"].startswith("too late: ") for u in uses
            )
            assert [f["revised"] for f in served["fixes"]] == [True]
        else:
            assert not any(u["reason"] and u["reason"].startswith("too late") for u in uses)
            assert served["fixes"][-1]["revised"]
        model.state, model.last_seq = state, body["seq"]
        model.epochs += sum(not fix.revised for fix in fixes)
        model.last_fix = served["fixes"][-1]
        model.last_body, model.last_response = body, response.content

    @rule(model=sessions, spaced=st.booleans())
    def retry_last_batch(self, model: Model, spaced: bool) -> None:
        if not model.live or model.last_body is None:
            return
        content = json.dumps(model.last_body, indent=2 if spaced else None)  # other bytes, same content
        response = self._post(model, content)
        assert response.status_code == 200 and response.content == model.last_response

    @rule(model=sessions, kind=st.sampled_from(BAD_KINDS), salt=st.text(max_size=8))
    def send_bad_request(self, model: Model, kind: str, salt: str) -> None:
        if not model.live:
            return
        seq = model.last_seq + 1
        first = min(model.next_epoch, len(EPOCHS) - 2)
        good = _measurements(first, 1)
        rsu = next(m for m in good if m["type"] == "rsu")
        body: Any = {"seq": seq, "measurements": good}
        expected = {422}
        if kind == "not_json":
            content: str | bytes = "{seq: 1, measurements: [" + salt
        elif kind == "truncated_json":
            content = json.dumps(body)[:-3]
        elif kind == "array_body":
            content = json.dumps([body])
        else:
            if kind == "wrong_type":
                rsu["range"] = "twelve metres" + salt
            elif kind == "huge_number":
                rsu["range"] = 1e308 * 10  # inf: serialised below as a JSON number too big for a double
            elif kind == "nan_literal":
                rsu["bearing"] = float("nan")
            elif kind == "unicode_rsu":
                rsu["rsu_id"] = "RSU-ü-" + salt + "\u202e"
            elif kind == "unknown_rsu":
                rsu["rsu_id"] = "nowhere-1"
            elif kind == "negative_range":
                rsu["range"] = -1.0
            elif kind == "too_late_unknown_rsu":  # too late for the lag window, but still validated
                if model.epochs == 0:
                    return
                for m in good:
                    m["t"] = model.last_fix["t"] - 2.0 * lag.DEFAULTS["max_delay_s"]
                rsu["rsu_id"] = "nowhere-1"
            elif kind == "clock_jump_in_batch":  # one measurement far after every other (max_lead_s)
                good[-1]["t"] = good[0]["t"] + 2.0 * lag.DEFAULTS["max_lead_s"]
            elif kind == "seq_gap":
                body["seq"], expected = seq + 1 + len(salt), {409}
            elif kind == "seq_zero":
                body["seq"] = 0
            elif kind == "seq_reused_other_body":
                if model.last_body is None or model.last_body["measurements"] == good:
                    return
                body["seq"], expected = model.last_seq, {409}
            elif kind == "too_many":
                body["measurements"] = (good * (MAX_MEASUREMENTS // len(good) + 1))[: MAX_MEASUREMENTS + 1]
            elif kind == "too_large":
                body["measurements"] = good * (MAX_BODY // 100)
                expected = {413}
            elif kind == "empty":
                body["measurements"] = []
            elif kind == "unknown_type":
                good[0]["type"] = "lidar" + salt
            elif kind == "bool_for_int":
                body["seq"] = True
            content = json.dumps(body, ensure_ascii=False).replace("Infinity", "1e999")
        response = self._post(model, content.encode() if isinstance(content, str) else content)
        assert response.status_code in expected, (kind, response.status_code, response.text)
        error = response.json()["error"]
        assert error["code"] and error["message"]
        assert response.status_code != 422 or error["problems"], response.text

    @rule(model=sessions, other=sessions)
    def use_another_sessions_token(self, model: Model, other: Model) -> None:
        if not model.live or not other.live or other is model:
            return
        response = CLIENT.get(f"/v1/sessions/{model.session_id}", headers=bearer(other.token))
        assert response.status_code == 403

    @rule(model=consumes(sessions))
    def delete_session(self, model: Model) -> None:
        if model.deleted:
            return
        response = CLIENT.delete(f"/v1/sessions/{model.session_id}", headers=bearer(model.token))
        if model.superseded_by is not None:
            self._assert_superseded(model, response)
            return
        assert response.status_code == 204
        model.deleted = True
        assert CLIENT.get(f"/v1/sessions/{model.session_id}", headers=ADMIN).status_code == 404

    @invariant()
    def sessions_hold_what_the_reference_says(self) -> None:
        for model in list(self.models):
            response = CLIENT.get(f"/v1/sessions/{model.session_id}", headers=ADMIN)
            if model.deleted:
                assert response.status_code == 404
                self.models.remove(model)  # checked once more after the delete; gone for good
                continue
            if model.superseded_by is not None:
                self._assert_superseded(model, response)
                own = CLIENT.get(f"/v1/sessions/{model.session_id}", headers=bearer(model.token))
                self._assert_superseded(model, own)
                self.models.remove(model)  # checked once; it can never come back
                continue
            assert response.status_code == 200, response.text
            info = response.json()
            assert (info["last_seq"], info["batches"], info["epochs"]) == (
                model.last_seq,
                model.last_seq,
                model.epochs,
            )
            assert info["last_fix"] == model.last_fix
            summary = PIPELINE.summarise(model.state)
            assert info["model_probabilities"] == summary.model_probabilities and info["t"] == summary.t

    def teardown(self) -> None:
        for model in list(self.models):
            if model.live:
                CLIENT.delete(f"/v1/sessions/{model.session_id}", headers=ADMIN)


TestApiBesideReference = ApiBesideReference.TestCase
TestApiBesideReference.settings = settings(
    max_examples=25,
    stateful_step_count=25,
    deadline=None,
    suppress_health_check=list(HealthCheck),
    derandomize=True,
)
