"""The committed openapi.json is the app's schema (regenerate: python -m edgepos.api.openapi)."""

from __future__ import annotations

from pathlib import Path

from edgepos.api.openapi import render, schema

ROOT = Path(__file__).resolve().parents[2]


def test_openapi_json_is_up_to_date():
    committed = (ROOT / "openapi.json").read_text(encoding="utf-8")
    assert committed == render(), "openapi.json is stale: run `python -m edgepos.api.openapi`"


def test_schema_documents_every_route_and_error():
    document = schema()
    paths = document["paths"]
    assert set(paths) == {
        "/v1/rsus",
        "/v1/rsus/{rsu_id}",
        "/v1/ephemerides",
        "/v1/base-stations",
        "/v1/base-stations/{station_id}",
        "/v1/base-stations/{station_id}/observations",
        "/v1/base-stations/{station_id}/rtcm",
        "/v1/pipelines",
        "/v1/sessions",
        "/v1/sessions/{session_id}",
        "/v1/sessions/{session_id}/batches",
        "/v1/sessions/{session_id}/track",
        "/v1/stream/fixes",
        "/v1/vehicles",
        "/v1/vehicles/bulk",
        "/v1/vehicles/{vehicle_id}",
        "/v1/vehicles/{vehicle_id}/key",
        "/v1/zones",
        "/v1/zones/{zone_id}",
        "/location/v3/queries/users",
        "/location/v3/queries/distance",
        "/location/v3/queries/zones",
        "/location/v3/queries/zones/{zoneId}",
        "/location/v3/subscriptions/users",
        "/location/v3/subscriptions/users/{subscriptionId}",
        "/location/v3/subscriptions/zones",
        "/location/v3/subscriptions/zones/{subscriptionId}",
        "/healthz",
        "/readyz",
        "/metrics",
        "/v1/status",
    }
    batches = paths["/v1/sessions/{session_id}/batches"]["post"]
    assert set(batches["responses"]) == {"200", "401", "403", "404", "409", "413", "415", "422", "429", "503"}
    assert batches["responses"]["422"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")
    assert document["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
    # the lag window's track: a GET with no body (no 413/415), every error a batch's GET neighbours have
    track = paths["/v1/sessions/{session_id}/track"]
    assert set(track) == {"get"}
    assert set(track["get"]["responses"]) == {"200", "401", "403", "404", "409", "422", "429", "503"}
    answers = track["get"]["responses"]
    assert answers["422"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")
    assert answers["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/TrackOut")
    query = {p["name"]: p for p in track["get"]["parameters"] if p["in"] == "query"}
    assert set(query) == {"smoothed"} and query["smoothed"]["schema"]["type"] == "boolean"
    assert query["smoothed"]["schema"]["default"] is False and query["smoothed"]["description"]
    upload = paths["/v1/ephemerides"]["put"]["requestBody"]["content"]
    assert set(upload) == {"text/plain", "application/octet-stream"}
    assert set(paths["/v1/ephemerides"]) == {"put", "get", "delete"}
    assert set(paths["/v1/base-stations"]) == {"post", "get"}
    assert set(paths["/v1/base-stations/{station_id}"]) == {"get", "delete"}
    rtcm = paths["/v1/base-stations/{station_id}/rtcm"]["post"]
    assert set(rtcm["requestBody"]["content"]) == {"application/octet-stream"}
    assert {"404", "413", "422"} <= set(rtcm["responses"])
    assert "404" in paths["/v1/sessions"]["post"]["responses"]  # an unknown options.base_station
    assert set(paths["/v1/sessions"]) == {"post", "get"}
    assert {"401", "403", "429"} <= set(paths["/v1/sessions"]["post"]["responses"])
    assert set(paths["/v1/vehicles"]) == {"post", "get"}
    assert set(paths["/v1/vehicles/{vehicle_id}"]) == {"get", "delete"}


def test_every_schema_field_is_described():
    missing = [
        f"{name}.{field}"
        for name, model in schema()["components"]["schemas"].items()
        if name not in {"ErrorBody"}
        for field, spec in model.get("properties", {}).items()
        if not spec.get("description") and "$ref" not in spec
    ]
    assert missing == []


def test_the_paths_are_listed_in_the_routers_order_not_in_the_order_requests_are_matched():
    """The batch route and the sessions router are matched first (the batch route takes most requests); the
    served document keeps the API's order, the registries first, the batches after the session's track
    (openapi.json sorts its keys, so only the served one shows it)."""
    paths = list(schema()["paths"])
    assert paths[:3] == ["/v1/rsus", "/v1/rsus/{rsu_id}", "/v1/ephemerides"]
    assert paths.index("/v1/pipelines") + 1 == paths.index("/v1/sessions")
    assert paths.index("/v1/sessions/{session_id}/track") + 1 == paths.index(
        "/v1/sessions/{session_id}/batches"
    )
