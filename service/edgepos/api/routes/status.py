"""``GET /v1/status``: the live figures the operator map's header shows (admin key)."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from edgepos.api.auth import require_admin
from edgepos.api.context import Context
from edgepos.api.routes import errors
from edgepos.api.schemas_status import OriginOut, StatusOut

PATH = "/v1/status"
router = APIRouter(tags=["health"])


@router.get(
    PATH,
    response_model=StatusOut,
    summary="Live service figures",
    dependencies=[Depends(require_admin)],
    responses=errors(401, 403, 429, 503),
)
async def get_status(context: Context) -> StatusOut:
    """Sessions, epochs/s, batches/s and the batch latency p99 of the last seconds, stream consumers, and the
    site's WGS-84 origin (admin key; a vehicle or session credential gets 403). Exact figures from one request,
    where /metrics has counters and bucketed histograms for Prometheus."""
    figures = context.metrics.recent.figures()
    origin = context.origin
    return StatusOut(
        sessions=await context.store.count(),
        window_s=figures.window_s,
        epochs_per_s=figures.epochs_per_s,
        batches_per_s=figures.batches_per_s,
        batch_latency_p99_s=figures.batch_latency_p99_s,
        batch_requests=figures.batch_requests,
        stream_consumers=context.stream_consumers,
        origin=None
        if origin is None
        else OriginOut(latitude=origin.lat, longitude=origin.lon, height=origin.height),
    )
