"""What every request handler needs, built once per app by ``create_app``."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Request

from edgepos.api.base_stations import EpochCache
from edgepos.api.ephemerides import EphemeridesCache
from edgepos.api.metrics import Metrics
from edgepos.api.middleware import Admission
from edgepos.api.scheduler import FairScheduler
from edgepos.api.settings import Settings
from edgepos.api.streams import StreamHub
from edgepos.api.vehicle_jwt import VehicleKeySet
from edgepos.geo import GeodeticOrigin
from edgepos.pipelines.base import Pipeline
from edgepos.store.base import SessionStore

Result = TypeVar("Result")


@dataclass
class AppContext:
    """Settings, store, pipelines, metrics and the estimation scheduler of one app instance.

    Estimation is CPU-bound work that holds the interpreter lock, so it never runs on the event loop:
    the scheduler (``api.scheduler``) runs it on this process's filter thread, or in worker processes
    when a batch is predicted to be heavy, serving vehicles in turn. Requests queue for it on the event
    loop, which meanwhile keeps serving everything else. Throughput scales with worker processes.
    """

    settings: Settings
    store: SessionStore
    pipelines: Mapping[str, Pipeline]
    metrics: Metrics
    origin: GeodeticOrigin | None
    admin_key_hash: bytes
    read_key_hash: bytes | None = None
    """SHA-256 of EDGEPOS_READ_KEY (opens the read-only location routes), None when it is not set."""
    ephemerides: EphemeridesCache = field(default_factory=EphemeridesCache)
    base_epochs: EpochCache = field(default_factory=EpochCache)
    """Decoded reference-station epochs of this worker (api.base_stations)."""
    vehicle_keys: VehicleKeySet | None = None
    """The fleet operator's public keys (EDGEPOS_VEHICLE_AUTH=jwt), loaded once at start-up."""
    admission: Admission | None = None
    """This worker's line of requests at work (EDGEPOS_MAX_INFLIGHT), set by ``create_app``: HTTP requests
    and WebSocket batch frames wait in it alike."""
    batch_sockets: int = 0
    """Batch WebSockets this worker holds open now (bounded by EDGEPOS_WS_MAX_CONNECTIONS)."""
    _scheduler: FairScheduler | None = field(default=None, repr=False)
    _streams: StreamHub | None = field(default=None, repr=False)

    @property
    def streams(self) -> StreamHub:
        """This worker's side of the fix stream (GET /v1/stream/fixes), over the store's fix log."""
        if self._streams is None:
            settings = self.settings
            self._streams = StreamHub(
                self.store.fix_log(settings.stream_buffer),
                self.metrics,
                queue=settings.stream_queue,
                max_consumers=settings.stream_max_consumers,
                ping_s=settings.stream_ping_s,
                interval_s=settings.stream_interval_ms / 1000.0,
            )
        return self._streams

    @property
    def stream_consumers(self) -> int:
        """Fix stream consumers of this worker (0 before the first one: the hub is not started for this)."""
        return 0 if self._streams is None else self._streams.consumer_count

    async def close_streams(self) -> None:
        """Write the fixes still waiting for the stream, stop the stream's tasks and close its log."""
        streams, self._streams = self._streams, None
        if streams is not None:
            await streams.close()

    @property
    def scheduler(self) -> FairScheduler:
        if self._scheduler is None:
            self._scheduler = FairScheduler(
                self.metrics,
                slice_s=self.settings.scheduler_slice_ms / 1000.0,
                heavy_workers=self.settings.heavy_workers,
                max_queued_per_key=self.settings.max_queued_per_vehicle,
                light_lane=self.settings.light_lane,
            )
        return self._scheduler

    async def run_filter(self, function: Callable[..., Result], *args: Any) -> Result:
        """Run the site's own CPU work (parsing ephemerides, warming the kernels) off the event loop, on
        a thread (FairScheduler.run_site)."""
        return await self.scheduler.run_site(function, *args)

    def stop_filter_thread(self) -> None:
        """Let the scheduler's thread and worker processes end once their current work is done."""
        if self._scheduler is not None:
            self._scheduler.shutdown()
            self._scheduler = None

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
