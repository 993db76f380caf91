"""Shared pieces of the client tests: the admin key, an app factory, the paper scenario's RSUs and
measurements as client models."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np
from edgepos.api.app import create_app
from edgepos.api.settings import Settings
from edgepos.loadgen.common import to_wire
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs
from edgepos_client import GyroMeasurement, Rsu, RsuMeasurement
from fastapi import FastAPI

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
    settings = Settings(admin_key=ADMIN_KEY, admin_key_file=tmp_path / "admin.key", **overrides)  # type: ignore[arg-type]
    return create_app(settings)
