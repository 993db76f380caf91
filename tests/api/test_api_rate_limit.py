"""Per-session request-rate limits: a burst passes, then 429 rate_limited with Retry-After; the
budget is per token (another vehicle and the admin key are unaffected; a wrong token spends none);
a refused batch changes nothing; and two workers sharing a store share the budget."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from apihelp import ADMIN, assert_error, batch_body, bearer, make_settings, open_session, rsu_payload
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from edgepos.loadgen.localredis import RedisServer
from edgepos.store import MemoryStore
from fastapi.testclient import TestClient

BURST = 4


def limited(tmp_path: Path, rate_per_s: float = 0.5, **overrides: object) -> Settings:
    return make_settings(tmp_path, rate_limit_per_s=rate_per_s, rate_limit_burst=BURST, **overrides)


class FrozenClock:
    """The store's clock, standing still: no budget comes back during the test however slowly it runs."""

    def __call__(self) -> float:
        return 1_000_000.0


def test_a_burst_then_429_with_retry_after(tmp_path):
    settings = limited(tmp_path)
    store = MemoryStore(settings.session_ttl_s, FrozenClock())
    with TestClient(create_app(settings, store=store)) as client:
        client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        session_id, token = open_session(client)
        other_id, other_token = open_session(client, vehicle_id="car-2")
        wrong = bearer(f"{session_id}.not-the-secret")
        for _ in range(10):  # invalid credentials spend nothing
            assert_error(client.get(f"/v1/sessions/{session_id}", headers=wrong), 401, "unauthorized")
        for seq in range(1, BURST + 1):
            response = client.post(
                f"/v1/sessions/{session_id}/batches", json=batch_body(seq, seq - 1, 1), headers=token
            )
            assert response.status_code == 200, response.text
        refused = client.post(
            f"/v1/sessions/{session_id}/batches", json=batch_body(BURST + 1, BURST, 1), headers=token
        )
        error = assert_error(refused, 429, "rate_limited")
        assert "EDGEPOS_RATE_LIMIT_PER_S" in error["message"]
        assert 1 <= int(refused.headers["Retry-After"]) <= 2
        for path in (f"/v1/sessions/{session_id}", "/v1/rsus", "/v1/rsus/S+000"):
            assert_error(client.get(path, headers=token), 429, "rate_limited")
        # the refused batch was not applied; the admin key is not limited; the other vehicle is not either
        assert client.get(f"/v1/sessions/{session_id}", headers=ADMIN).json()["last_seq"] == BURST
        assert client.get(f"/v1/sessions/{other_id}", headers=other_token).status_code == 200


def test_rate_limit_can_be_turned_off(tmp_path):
    settings = make_settings(tmp_path, rate_limit_per_s=0, rate_limit_burst=1)
    assert settings.rate_limit is None
    with TestClient(create_app(settings)) as client:
        session_id, token = open_session(client)
        for _ in range(20):
            assert client.get(f"/v1/sessions/{session_id}", headers=token).status_code == 200


def _shared_budget(first: TestClient, second: TestClient) -> None:
    """Two apps (as two workers) on one store: the token's burst is spent across both."""
    session_id, token = open_session(first)
    answers = [
        (first if n % 2 else second).get(f"/v1/sessions/{session_id}", headers=token).status_code
        for n in range(BURST + 2)
    ]
    assert answers == [200] * BURST + [429, 429]


# The two-worker tests run on real clocks (each app has its own store object); at 0.01 requests/s the
# budget comes back after 100 s, which no run of these few requests takes, however busy the machine.
SLOW_RATE_PER_S = 0.01


def test_two_workers_on_sqlite_share_the_budget(tmp_path):
    settings = limited(tmp_path, SLOW_RATE_PER_S, store=f"sqlite:///{tmp_path / 'shared.db'}")
    with TestClient(create_app(settings)) as first, TestClient(create_app(settings)) as second:
        _shared_budget(first, second)


@pytest.fixture
def redis_url(tmp_path: Path) -> Iterator[str]:
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    with RedisServer(binary, tmp_path / "redis", "--save", "", "--appendonly", "no") as server:
        yield server.url("ratelimit:")


def test_two_workers_on_redis_share_the_budget(tmp_path, redis_url):
    settings = limited(tmp_path, SLOW_RATE_PER_S, store=redis_url)
    with TestClient(create_app(settings)) as first, TestClient(create_app(settings)) as second:
        _shared_budget(first, second)
