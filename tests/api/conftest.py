"""Fixtures of the API tests: an app on the in-process store with the paper's RSU map loaded."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from apihelp import ADMIN, make_settings, rsu_payload
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from edgepos.loadgen.localredis import RedisServer
from fastapi.testclient import TestClient


@pytest.fixture(autouse=True)
def _clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tests configure the service explicitly, never from the caller's EDGEPOS_* variables."""
    for name in list(os.environ):
        if name.startswith("EDGEPOS_"):
            monkeypatch.delenv(name)


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return make_settings(tmp_path)


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    """A client of a fresh app whose registry holds the paper scenario's RSUs."""
    with TestClient(create_app(settings)) as test_client:
        response = test_client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN)
        assert response.status_code == 200, response.text
        yield test_client


@pytest.fixture(scope="module")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    """An in-memory redis-server (no persistence) for one test module; its tests keep apart by key prefix."""
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    server = RedisServer(binary, tmp_path_factory.mktemp("redis"), "--save", "", "--appendonly", "no")
    server.start()
    yield server
    server.stop()
