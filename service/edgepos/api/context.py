"""What every request handler needs, built once per app by ``create_app``."""

from __future__ import annotations

import asyncio
import functools
import hashlib
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Request

from edgepos.api.ephemerides import EphemeridesCache
from edgepos.api.metrics import Metrics
from edgepos.api.settings import Settings
from edgepos.api.vehicle_jwt import VehicleKeySet
from edgepos.geo import GeodeticOrigin
from edgepos.pipelines.base import Pipeline
from edgepos.store.base import SessionStore

Result = TypeVar("Result")


@dataclass
class AppContext:
    """Settings, store, pipelines and metrics of one app instance.

    Filtering runs on one dedicated thread per process. It is CPU-bound work that holds the GIL
    (Python, and compiled kernels too short to be worth releasing it), so more threads would not run
    it in parallel, only take turns at the GIL; with many batches in flight that convoy cost more
    than half the throughput. Requests queue for that thread on the event loop, which meanwhile
    keeps serving everything else: CPython makes the filter thread yield the GIL every switch
    interval (5 ms) when the loop waits for it. Throughput scales with worker processes.
    """

    settings: Settings
    store: SessionStore
    pipelines: Mapping[str, Pipeline]
    metrics: Metrics
    origin: GeodeticOrigin | None
    admin_key_hash: bytes
    ephemerides: EphemeridesCache = field(default_factory=EphemeridesCache)
    vehicle_keys: VehicleKeySet | None = None
    """The fleet operator's public keys (EDGEPOS_VEHICLE_AUTH=jwt), loaded once at start-up."""
    _filter_executor: ThreadPoolExecutor | None = field(default=None, repr=False)

    async def run_filter(self, function: Callable[..., Result], *args: Any) -> Result:
        """Run CPU-bound estimation work off the event loop, on the filter thread."""
        if self._filter_executor is None:
            self._filter_executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="edgepos-filter")
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._filter_executor, functools.partial(function, *args))

    def stop_filter_thread(self) -> None:
        """Let the filter thread end once its current work is done (app shutdown)."""
        if self._filter_executor is not None:
            self._filter_executor.shutdown(wait=False, cancel_futures=True)
            self._filter_executor = None

    @staticmethod
    def hash_admin_key(key: str) -> bytes:
        return hashlib.sha256(key.encode()).digest()


async def get_context(request: Request) -> AppContext:
    """FastAPI dependency: the app's context. A coroutine although it never awaits: FastAPI runs a
    plain function dependency in its threadpool, a thread hop (and GIL hand-off) per use."""
    context: AppContext = request.app.state.context
    return context


Context = Annotated[AppContext, Depends(get_context)]
"""Route parameter type that receives the app's context."""
