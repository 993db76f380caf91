"""Wire schema of GET /v1/status: the service's live figures and the site frame, for the operator map."""

from __future__ import annotations

from pydantic import Field

from edgepos.api.schemas import ResponseModel


class OriginOut(ResponseModel):
    """The WGS-84 point at the site frame's origin (EDGEPOS_ORIGIN_LAT/LON/HEIGHT)."""

    latitude: float = Field(description="Latitude of the site origin (rad, WGS-84).")
    longitude: float = Field(description="Longitude of the site origin (rad, east positive, WGS-84).")
    height: float = Field(description="Ellipsoidal height of the site origin (m).")


class StatusOut(ResponseModel):
    """Live figures for an operator: the sessions in the store, and what the worker that answered did during
    the last window_s seconds (with several workers each keeps its own; /metrics has the counters)."""

    sessions: int = Field(description="Live (unexpired) sessions in the store, all workers and replicas.")
    window_s: float = Field(description="Length of the window the rates and the p99 are over (s).")
    epochs_per_s: float = Field(description="Epochs filtered (fixes produced) per second by this worker.")
    batches_per_s: float = Field(description="Batches applied per second by this worker.")
    batch_latency_p99_s: float | None = Field(
        description="99th percentile (nearest rank) of the time to answer POST /v1/sessions/{session_id}/batches "
        "(s), every status, on this worker; null when it answered none in the window."
    )
    batch_requests: int = Field(description="Batch requests this worker answered in the window.")
    stream_consumers: int = Field(description="Fix stream consumers (GET /v1/stream/fixes) of this worker.")
    origin: OriginOut | None = Field(
        description="The site frame's WGS-84 origin (the site frame is the east-north tangent plane there), or "
        "null when none is configured."
    )
