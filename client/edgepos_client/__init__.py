"""Python client of the edgepos edge positioning service (API v1): sync and async, typed.

SI units and radians throughout; positions in the site-local east-north plane (m). See
:class:`EdgeposClient` and :class:`AsyncEdgeposClient`; every refusal raises an :class:`EdgeposError`.
"""

from edgepos_client._protocol import RetryPolicy, Session
from edgepos_client.async_client import AsyncEdgeposClient
from edgepos_client.errors import (
    Conflict,
    EdgeposError,
    EstimationFailed,
    Forbidden,
    InvalidRequest,
    MethodNotAllowed,
    NotFound,
    PayloadTooLarge,
    RateLimited,
    ServerError,
    TooManySessions,
    TransportError,
    Unauthorized,
    Unavailable,
)
from edgepos_client.models import (
    BatchResult,
    EphemeridesSummary,
    Fix,
    GnssFixMeasurement,
    GpsTime,
    GyroMeasurement,
    InitialState,
    Measurement,
    MeasurementUse,
    OdometerMeasurement,
    PipelineInfo,
    PipelineOption,
    Problem,
    PseudorangeMeasurement,
    RissMeasurement,
    Rsu,
    RsuMeasurement,
    RsuRangeMeasurement,
    SessionInfo,
    StateEstimate,
    V2vRangeMeasurement,
)
from edgepos_client.sync_client import EdgeposClient

__version__ = "0.1.0"

__all__ = [
    "AsyncEdgeposClient",
    "BatchResult",
    "Conflict",
    "EdgeposClient",
    "EdgeposError",
    "EphemeridesSummary",
    "EstimationFailed",
    "Fix",
    "Forbidden",
    "GnssFixMeasurement",
    "GpsTime",
    "GyroMeasurement",
    "InitialState",
    "InvalidRequest",
    "Measurement",
    "MeasurementUse",
    "MethodNotAllowed",
    "NotFound",
    "OdometerMeasurement",
    "PayloadTooLarge",
    "PipelineInfo",
    "PipelineOption",
    "Problem",
    "PseudorangeMeasurement",
    "RateLimited",
    "RetryPolicy",
    "RissMeasurement",
    "Rsu",
    "RsuMeasurement",
    "RsuRangeMeasurement",
    "ServerError",
    "Session",
    "SessionInfo",
    "StateEstimate",
    "TooManySessions",
    "TransportError",
    "Unauthorized",
    "Unavailable",
    "V2vRangeMeasurement",
]
