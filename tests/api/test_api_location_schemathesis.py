"""Schemathesis over the location adapter and the zones of an app with a site origin, zones, a located
vehicle and a subscription: no input gives a 5xx and every response matches the schema (problem details
included). Bounded: at most 40 examples per operation. (test_api_schemathesis covers the app without an
origin, where the adapter answers 409.)"""

from __future__ import annotations

from pathlib import Path

import schemathesis
from apihelp import ADMIN, ADMIN_KEY, batch_body, bearer, rsu_payload
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis.checks import positive_data_acceptance

_SETTINGS = Settings(
    admin_key=ADMIN_KEY,
    admin_key_file=Path("/nonexistent/never-written.key"),
    auth_failure_rate_per_s=1e6,
    auth_failure_burst=10**6,
    origin_lat=48.137,
    origin_lon=11.575,
    location_poll_s=60.0,  # no notifier poll during the run: the callbacks below lead nowhere
)
app = create_app(_SETTINGS)
client = TestClient(app)
client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
client.put("/v1/zones/gate", json={"circle": {"center": [90.0, 0.0], "radius": 15.0}}, headers=ADMIN)
_created = client.post("/v1/sessions", json={"vehicle_id": "car-1"}, headers=ADMIN).json()
client.post(
    f"/v1/sessions/{_created['session_id']}/batches",
    json=batch_body(1, 0, 20),
    headers=bearer(_created["token"]),
)

schema = schemathesis.openapi.from_asgi("/openapi.json", app).include(path_regex="^/(location/v3|v1/zones)")
BOUNDED = settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


@schema.parametrize()
@BOUNDED
def test_every_location_operation_conforms_to_the_schema(case):
    response = case.call_and_validate(headers=ADMIN, excluded_checks=[positive_data_acceptance])
    assert response.status_code < 500
