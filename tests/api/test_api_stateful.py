"""Stateful fuzzing: schemathesis follows the OpenAPI links of the app's schema (open a session ->
send batches -> read it -> delete it) with generated data, and checks every response against the
schema, no 5xx, and after each call that the session moved exactly as the answer says: a 200 batch
adds one to last_seq and its new (not revised) fixes to epochs, any refusal leaves the session as it
was, a 204 delete makes it 404. Some measurements are moved into the past of the session (late, within
or beyond its lag window)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import schemathesis
from apihelp import ADMIN, ADMIN_KEY, rsu_payload, scenario
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis.checks import ignored_auth, negative_data_rejection, positive_data_acceptance

_SETTINGS = Settings(
    admin_key=ADMIN_KEY, admin_key_file=Path("/nonexistent/never-written.key"), rate_limit_per_s=0
)
app = create_app(_SETTINGS)
client = TestClient(app)
client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
schema = schemathesis.openapi.from_asgi("/openapi.json", app)
RSU_IDS = [rsu.id for rsu in scenario().rsus]
# Every call carries the admin key, also those generated to lack one or with a wrong one, so "invalid
# data and bad credentials are refused" cannot hold for them (test_api_schemathesis.py and
# test_api_sessions.py check those); and schema-valid data can be refused for reasons a schema
# cannot state (see test_api_schemathesis.py).
EXCLUDED = [ignored_auth, negative_data_rejection, positive_data_acceptance]
SESSION_PATHS = {"/v1/sessions/{session_id}", "/v1/sessions/{session_id}/batches"}


def test_the_schema_links_the_session_workflow():
    links = {
        (path, method, name)
        for path, operations in app.openapi()["paths"].items()
        for method, operation in operations.items()
        for response in operation["responses"].values()
        for name in response.get("links", {})
    }
    assert ("/v1/sessions", "post", "SendBatch") in links
    assert ("/v1/sessions/{session_id}/batches", "post", "ReadSession") in links
    assert ("/v1/sessions/{session_id}", "get", "DeleteSession") in links
    operation_ids = {
        operation["operationId"]
        for operations in app.openapi()["paths"].values()
        for operation in operations.values()
    }
    for operations in app.openapi()["paths"].values():
        for operation in operations.values():
            for response in operation["responses"].values():
                for link in response.get("links", {}).values():
                    assert link["operationId"] in operation_ids  # a renamed route breaks loudly


def _session(session_id: Any) -> dict[str, Any] | None:
    if not isinstance(session_id, str):
        return None
    response = client.get(f"/v1/sessions/{session_id}", headers=ADMIN)
    return response.json() if response.status_code == 200 else None


def _delete_every_session() -> None:
    """Start each generated workflow from an empty store: hypothesis replays an example to shrink it,
    and a session list that grew with the examples before would draw different data on the replay
    (FlakyStrategyDefinition)."""
    while sessions := client.get("/v1/sessions", params={"limit": 1000}, headers=ADMIN).json()["sessions"]:
        for listed in sessions:
            assert client.delete(f"/v1/sessions/{listed['session_id']}", headers=ADMIN).status_code == 204


# The session workflow only: RSU writes in the mix would delete the map the batches need.
sessions_schema = schema.include(path_regex="^/v1/sessions")


class SessionWorkflow(sessions_schema.as_state_machine()):
    """Every call with the admin key; batches aimed at the next seq with known RSU ids so that many
    reach the filter; the session's state is compared before and after each call."""

    def setup(self) -> None:
        self.before: dict[str, Any] | None = None
        _delete_every_session()

    def before_call(self, case: Any) -> None:
        case.headers = {**(case.headers or {}), **ADMIN}
        self.before = None
        if case.operation.path not in SESSION_PATHS:
            return
        session_id = (case.path_parameters or {}).get("session_id")
        self.before = _session(session_id)
        if case.operation.path.endswith("/batches") and isinstance(case.body, dict) and self.before:
            case.body["seq"] = self.before["last_seq"] + 1
            newest = self.before["t"]
            for number, measurement in enumerate(case.body.get("measurements") or []):
                if isinstance(measurement, dict) and measurement.get("type") == "rsu":
                    measurement["rsu_id"] = RSU_IDS[number % len(RSU_IDS)]
                # Every third measurement late (inside or beyond the 1 s lag window): the window's
                # replays, revised fixes and too-late reports in the mix.
                if isinstance(measurement, dict) and newest is not None and number % 3 == 2:
                    measurement["t"] = newest - 0.25 * (number % 7)

    def after_call(self, response: Any, case: Any) -> None:
        assert response.status_code < 500, response.text
        if self.before is None:
            return
        after = _session(self.before["session_id"])
        method, path = case.operation.method.upper(), case.operation.path
        if method == "DELETE" and response.status_code == 204:
            assert after is None
            return
        assert after is not None
        if method == "POST" and path.endswith("/batches") and response.status_code == 200:
            assert after["last_seq"] == self.before["last_seq"] + 1
            assert after["batches"] == self.before["batches"] + 1
            fixes = response.json()["fixes"]
            assert after["epochs"] == self.before["epochs"] + sum(not fix["revised"] for fix in fixes)
            times = [fix["t"] for fix in fixes]
            assert times == sorted(times)
        else:
            unchanged = ("last_seq", "batches", "epochs", "t", "last_fix", "model_probabilities")
            assert {k: after[k] for k in unchanged} == {k: self.before[k] for k in unchanged}

    def validate_response(
        self, response: Any, case: Any, additional_checks: Any = None, **kwargs: Any
    ) -> None:
        case.validate_response(response, excluded_checks=EXCLUDED, transport_kwargs=kwargs)


TestSessionWorkflow = SessionWorkflow.TestCase
TestSessionWorkflow.settings = settings(
    max_examples=25,
    stateful_step_count=8,
    deadline=None,
    suppress_health_check=list(HealthCheck),
    derandomize=True,
)
