"""What every request handler needs, built once per app by ``create_app``."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request

from edgepos.api.metrics import Metrics
from edgepos.api.settings import Settings
from edgepos.geo import GeodeticOrigin
from edgepos.pipelines.base import Pipeline
from edgepos.store.base import SessionStore


@dataclass
class AppContext:
    """Settings, store, pipelines and metrics of one app instance."""

    settings: Settings
    store: SessionStore
    pipelines: Mapping[str, Pipeline]
    metrics: Metrics
    origin: GeodeticOrigin | None
    admin_key_hash: bytes

    @staticmethod
    def hash_admin_key(key: str) -> bytes:
        return hashlib.sha256(key.encode()).digest()


def get_context(request: Request) -> AppContext:
    """FastAPI dependency: the app's context."""
    context: AppContext = request.app.state.context
    return context


Context = Annotated[AppContext, Depends(get_context)]
"""Route parameter type that receives the app's context."""
