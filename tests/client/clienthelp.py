"""Shared pieces of the client tests: the admin key, an app factory, the paper scenario's RSUs and
measurements as client models, and a blocking transport into the app."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from edgepos.loadgen.common import to_wire
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs
from edgepos_client import GyroMeasurement, Rsu, RsuMeasurement
from fastapi import FastAPI
from fastapi.testclient import TestClient

ADMIN_KEY = "client-test-admin-key-0123456789"
INITIAL_STATE = {"x": 0.0, "y": 0.0, "vx": 10.0, "vy": 0.0}


@functools.lru_cache(maxsize=1)
def _epochs() -> tuple[tuple[RsuMeasurement | GyroMeasurement, ...], ...]:
    epochs = rsu_imu_epochs(rsu_imu_paper_scenario(), np.random.default_rng(11))
    return tuple(tuple(to_wire(o) for o in epoch) for epoch in epochs)


def batch(first: int, count: int) -> list[RsuMeasurement | GyroMeasurement]:
    """Measurements of epochs first .. first+count-1 (0-based)."""
    return [m for epoch in _epochs()[first : first + count] for m in epoch]


def scenario_rsus() -> list[Rsu]:
    return [Rsu(id=rsu.id, x=rsu.x, y=rsu.y) for rsu in rsu_imu_paper_scenario().rsus]


def make_app(tmp_path: Path, **overrides: Any) -> FastAPI:
    settings = Settings(admin_key=ADMIN_KEY, admin_key_file=tmp_path / "admin.key", **overrides)
    return create_app(settings)


class TestClientTransport(httpx.BaseTransport):
    """A blocking transport into the app through Starlette's TestClient (its lifespan run), for the sync
    client in-process: each request goes through the TestClient as the client built it, percent-encoded
    path included, and the answer comes back as a plain response."""

    __test__ = False  # not a test class, whatever pytest makes of its name

    def __init__(self, client: TestClient) -> None:
        self.client = client

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        answer = self.client.send(request)
        headers = [(k, v) for k, v in answer.headers.multi_items() if k.lower() not in _HOP_HEADERS]
        return httpx.Response(answer.status_code, headers=headers, content=answer.content)


_HOP_HEADERS = {"content-encoding", "content-length", "transfer-encoding"}
