"""Schemathesis over the app's own schema: no input gives a 5xx and every response (status, content
type, headers, body) matches the schema. Bounded: at most 40 examples per operation.

``positive_data_acceptance`` is left out here: some schema-valid requests are refused by rules a
JSON schema cannot state (unique RSU ids in one request, the next seq, a known RSU), and those
refusals are 4xx with the documented error body. test_api_schemathesis_live runs every check against
the real server and allows exactly those documented refusals.
"""

from __future__ import annotations

from pathlib import Path

import schemathesis
from apihelp import ADMIN, ADMIN_KEY, bearer, rsu_payload, scenario
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import negative_data_rejection, positive_data_acceptance

# Schemathesis sends thousands of requests without or with wrong credentials on purpose: the failure
# budget (tested in test_api_vehicles) is lifted so that every answer is the route's own.
_SETTINGS = Settings(
    admin_key=ADMIN_KEY,
    admin_key_file=Path("/nonexistent/never-written.key"),
    auth_failure_rate_per_s=1e6,
    auth_failure_burst=10**6,
)
app = create_app(_SETTINGS)
client = TestClient(app)
client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)

# The fix stream's 200 never ends (server-sent events until the consumer leaves): schemathesis would wait for
# its end forever. Its refusals and events are tested in test_api_streams.
schema = schemathesis.openapi.from_asgi("/openapi.json", app).exclude(path="/v1/stream/fixes")
# Both tests send every case with a valid credential of their own, replacing an Authorization header that a
# negative case may have dropped or mangled on purpose; and a negative query's extra parameter can be one the
# client leaves out (a null value). The request that goes out is then valid, so "negative data must be
# rejected" judged a valid request: it failed on GET /v1/vehicles?after=e whenever hypothesis's pool of
# constants from the code happened to generate that case. What a route refuses is tested where each refusal
# is specified (the test_api_* files of each route, and the fuzz tests of options, GNSS and cooperative
# schemas); these tests hold every answer to its documented schema and status, and no answer to be a 5xx.
EXCLUDED = [positive_data_acceptance, negative_data_rejection]
RSU_IDS = [rsu.id for rsu in scenario().rsus]
BOUNDED = settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


@schema.parametrize()
@BOUNDED
def test_every_operation_conforms_to_the_schema(case):
    response = case.call_and_validate(headers=ADMIN, excluded_checks=EXCLUDED)
    assert response.status_code < 500


@given(case=schema["/v1/sessions/{session_id}/batches"]["POST"].as_strategy())
@BOUNDED
def test_fuzzed_batches_on_a_live_session(case):
    """Schema-valid batches aimed at a real session (seq 1, known RSU ids), so they reach the
    filter: every answer is 200 or a documented 4xx, and a refused batch changes nothing."""
    created = client.post("/v1/sessions", json={"vehicle_id": "fuzz"}, headers=ADMIN).json()
    session_id = created["session_id"]
    case.path_parameters = {"session_id": session_id}
    if isinstance(case.body, dict):
        case.body["seq"] = 1
        for number, measurement in enumerate(case.body.get("measurements") or []):
            if isinstance(measurement, dict) and measurement.get("type") == "rsu":
                measurement["rsu_id"] = RSU_IDS[number % len(RSU_IDS)]
    response = case.call_and_validate(headers=bearer(created["token"]), excluded_checks=EXCLUDED)
    assert response.status_code < 500
    info = client.get(f"/v1/sessions/{session_id}", headers=ADMIN).json()
    assert info["last_seq"] == (1 if response.status_code == 200 else 0)
    client.delete(f"/v1/sessions/{session_id}", headers=ADMIN)
