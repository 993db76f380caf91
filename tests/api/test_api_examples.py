"""What Swagger's "Try it out" sends is accepted: every JSON request body's schema example, posted to its
route on a fresh test app (the paper's RSU map loaded), answers 2xx. Also the short operation ids that
generated clients name their functions after, and the bare address sending people to /docs."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
from apihelp import ADMIN, make_settings, rsu_payload
from edgepos.api.app import create_app
from edgepos.api.openapi import schema
from fastapi.testclient import TestClient

DOCUMENT = schema()
SCHEMAS = DOCUMENT["components"]["schemas"]


def _json_operations() -> list[tuple[str, str, str]]:
    """(method, path, schema name) of every operation with a JSON request body."""
    found = []
    for path, methods in DOCUMENT["paths"].items():
        for method, operation in methods.items():
            content = operation.get("requestBody", {}).get("content", {})
            if "application/json" in content:
                ref = content["application/json"]["schema"]["$ref"]
                found.append((method, path, ref.rsplit("/", 1)[-1]))
    return found


def _example(name: str) -> dict[str, Any]:
    examples = SCHEMAS[name].get("examples")
    assert examples, f"request model {name} has no example for Swagger's Try it out"
    return examples[0]


@pytest.fixture
def site_client(tmp_path: Path):
    settings = make_settings(tmp_path, origin_lat=48.86, origin_lon=11.5)
    with TestClient(create_app(settings)) as test_client:
        assert test_client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
        yield test_client


@pytest.mark.parametrize(("method", "path", "name"), _json_operations())
def test_each_request_example_is_accepted(site_client: TestClient, method: str, path: str, name: str):
    # The resources an example refers to, made from the other examples: a session for its batch, the
    # zone 'depot' for a zone subscription (both stated in the schema's descriptions).
    parameters = {"rsu_id": "S+000", "zone_id": "depot"}
    if "{session_id}" in path:
        created = site_client.post("/v1/sessions", json=_example("SessionCreate"), headers=ADMIN)
        assert created.status_code == 201, created.text
        parameters["session_id"] = created.json()["session_id"]
    if name == "ZoneLocationEventSubscriptionIn":
        zone = site_client.put("/v1/zones/depot", json=_example("ZoneIn"), headers=ADMIN)
        assert zone.status_code in (200, 201), zone.text
    url = re.sub(r"\{(\w+)\}", lambda match: parameters[match.group(1)], path)
    response = site_client.request(method.upper(), url, json=_example(name), headers=ADMIN)
    assert 200 <= response.status_code < 300, (method, path, response.status_code, response.text)


def test_every_json_request_body_is_covered():
    names = {name for _, _, name in _json_operations()}
    assert {"SessionCreate", "BatchIn", "RsuBulk", "RsuPut", "ZoneIn", "BaseStationIn"} <= names


def test_operation_ids_are_short_unique_identifiers():
    ids = [
        operation["operationId"] for methods in DOCUMENT["paths"].values() for operation in methods.values()
    ]
    assert len(ids) == len(set(ids))
    assert all(re.fullmatch(r"[a-z][a-z_]{2,30}", operation_id) for operation_id in ids), ids
    by_route = {
        (method, path): operation["operationId"]
        for path, methods in DOCUMENT["paths"].items()
        for method, operation in methods.items()
    }
    assert by_route[("post", "/v1/sessions")] == "create_session"
    assert by_route[("post", "/v1/sessions/{session_id}/batches")] == "post_batch"
    assert by_route[("get", "/v1/rsus")] == "list_rsus"


def test_schema_states_what_json_schema_can():
    pipeline = SCHEMAS["SessionCreate"]["properties"]["pipeline"]
    assert pipeline["enum"] == ["gnss_tight", "rsu_imu", "v2v_coop", "v2x_federated"]
    for name, pair in (
        ("OdometerMeasurement", ["distance", "speed"]),
        ("V2vRangeMeasurement", ["range", "toa"]),
        ("ZoneIn", ["circle", "polygon"]),
    ):
        both, neither = SCHEMAS[name]["not"]["anyOf"]
        assert both["required"] == pair
        assert neither["properties"] == {field: {"type": "null"} for field in pair}
    assert "repeated id is refused" in SCHEMAS["RsuBulk"]["description"]
    assert "differs from the path" in SCHEMAS["RsuPut"]["description"]
    for path in ("/v1/ephemerides", "/v1/base-stations/{station_id}/observations"):
        methods = DOCUMENT["paths"][path]
        content = (methods.get("put") or methods["post"])["requestBody"]["content"]
        assert content["application/octet-stream"]["schema"] == {"type": "string", "format": "binary"}
        assert content["text/plain"]["schema"]["type"] == "string"


def test_the_bare_address_redirects_to_the_docs(client: TestClient):
    response = client.get("/", follow_redirects=False)
    assert response.status_code == 307
    assert response.headers["location"] == "/docs"
    assert "/" not in DOCUMENT["paths"]
