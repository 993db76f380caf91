"""Liveness, readiness and Prometheus metrics (public: they carry no site or vehicle data)."""

from __future__ import annotations

import asyncio
import logging

from fastapi import APIRouter, Response

from edgepos.api.context import Context
from edgepos.api.errors import ApiError
from edgepos.api.metrics import CONTENT_TYPE
from edgepos.api.routes import errors
from edgepos.api.schemas import Health, Ready

router = APIRouter(tags=["health"])
logger = logging.getLogger("edgepos.api")

READY_TIMEOUT_S = 2.0


@router.get("/healthz", response_model=Health, summary="Liveness")
async def healthz() -> Health:
    """200 while the process serves requests."""
    return Health(status="ok")


@router.get("/readyz", response_model=Ready, summary="Readiness", responses=errors(503))
async def readyz(context: Context) -> Ready:
    """200 when the session store answers within 2 s, else 503."""
    try:
        await asyncio.wait_for(context.store.ping(), READY_TIMEOUT_S)
    except Exception as error:  # noqa: BLE001 - any store failure (timeout, transport, protocol) means "not ready", never a 500
        logger.warning("store not ready", extra={"event": "not_ready", "error": repr(error)})
        raise ApiError("unavailable", "the session store does not answer") from None
    return Ready(status="ready")


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"description": "Prometheus text exposition format.", "content": {"text/plain": {}}}},
)
async def metrics(context: Context) -> Response:
    """Request counts and latency histograms by route and status, active sessions, epochs processed,
    filter step time."""
    body = context.metrics.render(await context.store.count())
    return Response(body, media_type=CONTENT_TYPE)
