"""GNSS over a real socket: ``edgepos serve`` with two workers on a real redis-server, the navigation file
uploaded through one connection (and a streamed oversized one refused), the recording's pseudoranges sent
over fresh connections so that both workers serve batches with the shared ephemerides."""

from __future__ import annotations

import shutil

import httpx
import pytest
from edgepos.loadgen.localredis import RedisServer
from gnsswire import QUICK, horizontal_error, measurements, nav_text
from test_api_server import running_server

pytestmark = pytest.mark.slow


def test_gnss_tight_over_a_real_socket_on_two_redis_workers(tmp_path):
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    key = "gnss-socket-admin-key-0123456789"
    admin = {"Authorization": f"Bearer {key}"}
    size = len(nav_text().encode())
    with (
        RedisServer(binary, tmp_path / "redis", "--save", "", "--appendonly", "no") as redis_server,
        running_server(
            tmp_path,
            "--workers",
            "2",
            EDGEPOS_STORE=redis_server.url("socket:"),
            EDGEPOS_ADMIN_KEY=key,
            EDGEPOS_MAX_EPHEMERIDES_BYTES=str(size),
        ) as (url, _),
    ):
        with httpx.Client(base_url=url, timeout=30.0) as client:

            def streamed():  # no Content-Length: counted chunk by chunk
                for _ in range(size // 1000 + 1):
                    yield b"x" * 1000

            refused = client.put("/v1/ephemerides", content=streamed(), headers=admin)
            assert refused.status_code == 413 and "EDGEPOS_MAX_EPHEMERIDES_BYTES" in refused.text
            uploaded = client.put(
                "/v1/ephemerides", content=nav_text(), headers={**admin, "Content-Type": "text/plain"}
            )
            assert uploaded.status_code == 200, uploaded.text
            created = client.post(
                "/v1/sessions",
                json={"vehicle_id": "socket-gnss", "pipeline": "gnss_tight", "options": QUICK},
                headers=admin,
            ).json()
        token = {"Authorization": f"Bearer {created['token']}"}
        fixes = []
        for seq in range(1, 11):
            with httpx.Client(base_url=url, timeout=30.0) as client:  # a new connection per batch
                response = client.post(
                    f"/v1/sessions/{created['session_id']}/batches",
                    json={"seq": seq, "measurements": measurements(seq - 1, 1)},
                    headers=token,
                )
                assert response.status_code == 200, response.text
                fixes.extend(response.json()["fixes"])
                summary = client.get("/v1/ephemerides", headers=token).json()
                assert summary["digest"] == uploaded.json()["digest"]
    assert [fix["status"] for fix in fixes] == ["initialised"] + ["tracking"] * 9
    errors = [e for e in (horizontal_error(fix) for fix in fixes) if e is not None]
    assert len(errors) >= 8 and max(errors) < 10.0, errors
