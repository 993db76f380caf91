"""A store that does not answer gives 503 with Retry-After, never a 500 or a hang."""

from __future__ import annotations

import socket
import time

from apihelp import ADMIN, ADMIN_KEY, make_settings
from edgepos.api.app import create_app
from fastapi.testclient import TestClient


def closed_port() -> int:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_unreachable_redis_gives_503_and_a_failing_readiness(tmp_path):
    store = f"redis://127.0.0.1:{closed_port()}/0"
    app = create_app(make_settings(tmp_path, store=store, demo_rsus=True))
    with TestClient(app) as client:  # starts although the demo RSUs cannot be loaded
        started = time.monotonic()
        response = client.post("/v1/sessions", json={"vehicle_id": "car-1"}, headers=ADMIN)
        assert time.monotonic() - started < 5.0
        assert response.status_code == 503
        assert response.json()["error"]["code"] == "unavailable"
        assert "127.0.0.1" not in response.json()["error"]["message"]
        assert int(response.headers["Retry-After"]) >= 1
        rsus = client.get("/v1/rsus", headers={"Authorization": f"Bearer {ADMIN_KEY}"})
        assert rsus.status_code == 503
        assert client.get("/readyz").status_code == 503
        assert client.get("/healthz").status_code == 200
