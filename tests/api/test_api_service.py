"""Cross-cutting behaviour: error shape for unknown routes, request ids, the catch-all 500, logs
without secrets, the generated admin key, metrics, health, offline docs and CORS."""

from __future__ import annotations

import gc
import json
import os
import re
import stat

from apifakes import BrokenPipeline
from apihelp import (
    ADMIN,
    ADMIN_KEY,
    assert_error,
    batch_body,
    bearer,
    make_settings,
    open_session,
    rsu_payload,
)
from edgepos.api.app import YOUNG_GC_THRESHOLD, create_app
from edgepos.api.settings import Settings
from edgepos.store import MemoryStore
from fastapi.testclient import TestClient


def test_unknown_route_and_method_use_the_error_body(client):
    assert_error(client.get("/v2/nothing"), 404, "not_found")
    assert_error(client.patch("/v1/rsus", json={}), 405, "method_not_allowed")


def test_request_id_is_echoed_or_generated(client):
    response = client.get("/healthz", headers={"X-Request-ID": "abc-123"})
    assert response.headers["x-request-id"] == "abc-123"
    generated = client.get("/healthz", headers={"X-Request-ID": "bad id with spaces"}).headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", generated)


def test_a_bug_gives_a_generic_500_that_reveals_nothing(tmp_path, capfd):
    app = create_app(make_settings(tmp_path), pipelines={"rsu_imu": BrokenPipeline()})
    with TestClient(app) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        response = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 1), headers=token)
        error = assert_error(response, 500, "internal_error")
        assert "secret-looking" not in response.text
        assert response.headers["x-request-id"]
        assert client.get(f"/v1/sessions/{session_id}", headers=token).json()["last_seq"] == 0
    logged = capfd.readouterr().err
    assert "unhandled error" in logged and "secret-looking" in logged  # the traceback goes to the log
    assert error["problems"] == []


def test_logs_are_json_lines_without_keys_or_tokens(tmp_path, capfd):
    with TestClient(create_app(make_settings(tmp_path))) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        created = client.post("/v1/sessions", json={"vehicle_id": "car"}, headers=ADMIN).json()
        token = created["token"]
        session_id = created["session_id"]
        client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 2), headers=bearer(token))
        client.get(f"/v1/sessions/{session_id}", headers=bearer(token + "x"))
        client.get(f"/v1/sessions/{session_id}?token={token}", headers=bearer(ADMIN_KEY))
        client.get("/v1/rsus", headers=bearer("wrong-" + ADMIN_KEY))
    logged = capfd.readouterr().err
    lines = [line for line in logged.splitlines() if line.strip()]
    assert lines
    entries = [json.loads(line) for line in lines]
    requests = [e for e in entries if e.get("event") == "request"]
    assert len(requests) == 6
    assert all(e["request_id"] and e["route"] and "duration_ms" in e for e in requests)
    assert {e["route"] for e in requests} >= {
        "/v1/sessions/{session_id}/batches",
        "/v1/sessions/{session_id}",
    }
    secret = token.split(".", 1)[1]
    assert ADMIN_KEY not in logged and secret not in logged and token not in logged


def test_generated_admin_key_is_printed_once_and_saved_privately(tmp_path, capfd):
    key_file = tmp_path / "keys" / "admin.key"
    settings = Settings(admin_key_file=key_file)
    with TestClient(create_app(settings)) as client:
        key = key_file.read_text().strip()
        assert len(key) >= 40
        assert stat.S_IMODE(os.stat(key_file).st_mode) == 0o600
        assert client.put("/v1/rsus", json=rsu_payload(), headers=bearer(key)).status_code == 200
        session_id, token = open_session(client, bearer(key))
        client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 1), headers=token)
        client.get("/v1/rsus", headers=bearer(key))
    err = capfd.readouterr().err
    assert err.count(key) == 1
    assert str(key_file) in err


def test_metrics_count_requests_epochs_and_sessions(client):
    session_id, token = open_session(client)
    client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 6), headers=token)
    client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 6), headers=token)
    open_session(client, vehicle_id="car-2")
    response = client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    text = response.text
    route = 'route="/v1/sessions/{session_id}/batches"'
    assert f'edgepos_http_requests_total{{method="POST",{route},status="200"}} 2.0' in text
    assert f'edgepos_http_request_duration_seconds_count{{method="POST",{route},status="200"}} 2.0' in text
    assert "edgepos_active_sessions 2.0" in text
    assert "edgepos_epochs_processed_total 6.0" in text
    assert "edgepos_filter_step_seconds_count 1.0" in text
    assert 'edgepos_batches_total{outcome="replayed"} 1.0' in text
    assert 'edgepos_batches_total{outcome="applied"} 1.0' in text
    assert session_id not in text


def test_metrics_method_label_is_bounded(client):
    """The method label comes from the client: methods outside the usual few share one label value, so
    a client cannot add time series without end."""
    for method in ("PROPFIND", "MKCALENDAR", "PURGE"):
        assert client.request(method, "/healthz").status_code == 405
    client.request("OPTIONS", "/healthz")
    text = client.get("/metrics").text
    assert 'edgepos_http_requests_total{method="other",route="/healthz",status="405"} 3.0' in text
    assert 'method="OPTIONS",route="/healthz"' in text
    for method in ("PROPFIND", "MKCALENDAR", "PURGE"):
        assert f'method="{method}"' not in text


def test_health_and_readiness(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json() == {"status": "ready"}


class DeadStore(MemoryStore):
    async def ping(self) -> bool:
        raise ConnectionError("store is down")


def test_readiness_fails_when_the_store_does_not_answer(tmp_path):
    with TestClient(create_app(make_settings(tmp_path), store=DeadStore(60.0))) as client:
        assert_error(client.get("/readyz"), 503, "unavailable")
        assert client.get("/healthz").status_code == 200


def test_docs_pages_use_only_bundled_assets(client):
    for page in ("/docs", "/redoc"):
        response = client.get(page)
        assert response.status_code == 200 and "text/html" in response.headers["content-type"]
        html = response.text
        assert "http://" not in html and "https://" not in html, page
        assets = re.findall(r'(?:src|href)="([^"]+)"', html)
        assert assets and all(a.startswith("/static/") for a in assets)
        for asset in assets:
            fetched = client.get(asset)
            assert fetched.status_code == 200 and len(fetched.content) > 500, asset
    assert client.get("/openapi.json").json()["info"]["title"] == "edgepos"


def test_static_assets_ship_with_their_licenses():
    from importlib import resources

    static = resources.files("edgepos.api") / "static"
    assert (static / "swagger-ui" / "LICENSE").is_file()
    assert (static / "redoc" / "LICENSE").is_file()


def test_cors_is_off_by_default_and_on_when_configured(client, tmp_path):
    preflight = {"Origin": "https://ops.example", "Access-Control-Request-Method": "POST"}
    assert "access-control-allow-origin" not in client.options("/v1/sessions", headers=preflight).headers
    with TestClient(create_app(make_settings(tmp_path, cors_origins="https://ops.example"))) as cors_client:
        response = cors_client.options("/v1/sessions", headers=preflight)
        assert response.headers["access-control-allow-origin"] == "https://ops.example"


def test_demo_rsus_preload_the_paper_map(tmp_path):
    from apihelp import scenario

    with TestClient(create_app(make_settings(tmp_path, demo_rsus=True))) as client:
        rsus = client.get("/v1/rsus", headers=ADMIN).json()["rsus"]
    assert sorted(r["id"] for r in rsus) == sorted(r.id for r in scenario().rsus)


def test_redaction_filter_scrubs_credential_shaped_text():
    import logging

    from edgepos.api.logs import JsonFormatter, RedactSecrets

    token = "0123456789abcdef0123456789abcdef.Zx9_secretpart-1234567890"
    record = logging.makeLogRecord(
        {"msg": "auth %s and %s", "args": ("Bearer abc.def", token), "detail": f"key {ADMIN_KEY}"}
    )
    assert RedactSecrets([ADMIN_KEY]).filter(record)
    line = json.loads(JsonFormatter().format(record))
    assert line["message"] == "auth [redacted] and [redacted]"
    assert line["detail"] == "key [redacted]"


def test_redaction_finds_what_the_replacements_would_change():
    """The filter's one search before replacing (most texts hold no secret) misses nothing: on texts
    pieced from credentials, near-misses and ordinary text it scrubs as the replacements alone do."""
    import random

    from edgepos.api.logs import _SECRET_PATTERNS, REDACTED, RedactSecrets

    secrets = [ADMIN_KEY, "reader.key+with(regex)chars"]
    redact = RedactSecrets(secrets)

    def replaced(text: str) -> str:
        for secret in secrets:
            text = text.replace(secret, REDACTED)
        for pattern in _SECRET_PATTERNS:
            text = pattern.sub(REDACTED, text)
        return text

    pieces = [
        *secrets,
        ADMIN_KEY[:-1],
        "Bearer",
        "bEaReR",
        " ",
        "\t",
        "abc.def",
        "0123456789abcdef0123456789abcdef",
        ".",
        "Zx9_secretpart-123456",
        "short",
        "/v1/sessions/",
        "/batches",
        "POST",
        "reader.key",
    ]
    rng = random.Random(19)
    changed = 0
    for _ in range(3000):
        text = "".join(rng.choice(pieces) for _ in range(rng.randint(0, 6)))
        assert redact.scrub(text) == replaced(text), text
        changed += replaced(text) != text
    assert changed > 500


def test_startup_freezes_the_long_lived_heap(tmp_path):
    """Full collections must not walk the libraries' objects on every pass (50-100 ms pauses under load)."""
    gc.unfreeze()
    assert gc.get_freeze_count() == 0
    with TestClient(create_app(make_settings(tmp_path))) as client:
        assert client.get("/healthz").status_code == 200
        assert gc.get_freeze_count() > 10_000


def test_young_collections_are_rarer_while_serving(tmp_path):
    """A batch's short-lived objects do not set off a collection each (YOUNG_GC_THRESHOLD); the thresholds
    are the process's own again once the app stops."""
    before = gc.get_threshold()
    with TestClient(create_app(make_settings(tmp_path))) as client:
        assert client.get("/healthz").status_code == 200
        assert gc.get_threshold() == (YOUNG_GC_THRESHOLD, *before[1:])
    assert gc.get_threshold() == before
