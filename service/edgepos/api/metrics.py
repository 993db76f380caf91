"""Prometheus metrics of one app instance (one registry per app, so tests can run several).

With several workers each process keeps its own counters and a scrape sees the worker that
answered it; ``edgepos_active_sessions`` is read from the store, so it is the same in all.
"""

from __future__ import annotations

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

from edgepos.api.recent import RecentWindow

_LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
_STEP_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1)

CONTENT_TYPE = CONTENT_TYPE_LATEST

#: The request methods the ``method`` label keeps (and ``WS``, a batch's frame on the WebSocket); any other
#: is counted as ``other``. The method comes from the client: uvicorn's httptools parser accepts some thirty,
#: h11 (its fallback) any token, and every distinct label value is a new time series kept for the life of
#: the process.
LABELLED_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS", "WS"})

BATCH_ROUTE = "/v1/sessions/{session_id}/batches"
"""The route whose latency the operator map's header shows (GET /v1/status)."""


class Metrics:
    """Request counts and latencies by route template and status; session and filter figures."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.recent = RecentWindow()
        """The last seconds' epochs/s, batches/s and batch latency p99 (GET /v1/status)."""
        self.requests = Counter(
            "edgepos_http_requests",
            "HTTP requests answered, by method, route template and status.",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "edgepos_http_request_duration_seconds",
            "Time from request start to the end of the response, by method, route template and status.",
            ["method", "route", "status"],
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.active_sessions = Gauge(
            "edgepos_active_sessions", "Live (unexpired) sessions in the store.", registry=self.registry
        )
        self.epochs = Counter(
            "edgepos_epochs_processed",
            "Epochs filtered (fixes produced) by applied batches.",
            registry=self.registry,
        )
        self.batches = Counter(
            "edgepos_batches",
            "Batches by outcome: applied, replayed, rejected, conflict, failed.",
            ["outcome"],
            registry=self.registry,
        )
        self.filter_step = Histogram(
            "edgepos_filter_step_seconds",
            "Mean filter time per epoch of each processed batch (pipeline time / epochs).",
            buckets=_STEP_BUCKETS,
            registry=self.registry,
        )
        self.pipeline_batch = Histogram(
            "edgepos_pipeline_batch_seconds",
            "Time the pipeline took to process one batch (worker thread).",
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.waiting = Gauge(
            "edgepos_requests_waiting",
            "Requests of this worker waiting for a free slot (EDGEPOS_MAX_INFLIGHT) before being worked on.",
            registry=self.registry,
        )
        self.store_conflicts = Counter(
            "edgepos_store_conflicts",
            "Compare-and-set conflicts on session writes (another worker updated the session first).",
            registry=self.registry,
        )

        self.auth_failures = Counter(
            "edgepos_auth_failures",
            "Refused authentications by reason: missing, invalid, forbidden, wrong_vehicle.",
            ["reason"],
            registry=self.registry,
        )
        self.rate_limited = Counter(
            "edgepos_rate_limited",
            "Requests answered 429 by the budget they exceeded: session_requests, auth_failures, "
            "session_creations.",
            ["limit"],
            registry=self.registry,
        )
        self.sessions_superseded = Counter(
            "edgepos_sessions_superseded",
            "Sessions ended because a newer session was opened for the same vehicle.",
            registry=self.registry,
        )
        self.vehicles_revoked = Counter(
            "edgepos_vehicles_revoked",
            "Vehicles removed from the registry (DELETE /v1/vehicles/{id}).",
            registry=self.registry,
        )

        self.queue_depth = Gauge(
            "edgepos_scheduler_queue_depth",
            "Estimation jobs waiting for their turn, by lane (light: this process's filter thread; heavy: "
            "the worker processes).",
            ["lane"],
            registry=self.registry,
        )
        self.queue_wait = Histogram(
            "edgepos_scheduler_wait_seconds",
            "Time an estimation job waited for its turn, by lane.",
            ["lane"],
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.pipeline_cpu = Counter(
            "edgepos_pipeline_cpu_seconds",
            "CPU seconds spent filtering, by pipeline (session creation and batches).",
            ["pipeline"],
            registry=self.registry,
        )

        self.stream_consumers = Gauge(
            "edgepos_stream_consumers",
            "Fix stream consumers (GET /v1/stream/fixes) connected to this worker.",
            registry=self.registry,
        )
        self.stream_events_sent = Counter(
            "edgepos_stream_events_sent",
            "Fix events this worker sent to stream consumers.",
            registry=self.registry,
        )
        self.stream_events_dropped = Counter(
            "edgepos_stream_events_dropped",
            "Fix events not sent, by reason: slow_consumer (a consumer fell EDGEPOS_STREAM_QUEUE behind and was "
            "dropped), decimated (max_rate_hz), publish_backlog (this worker's stream writes fell behind), "
            "store_unavailable (the store refused the stream write).",
            ["reason"],
            registry=self.registry,
        )
        # labels() takes a lock and checks its arguments on every call (1.4 us each, three a batch): the
        # children of the labels every request and batch uses are looked up once
        self._request_children: dict[tuple[str, str, int], tuple[Counter, Histogram]] = {}
        self._applied = self.batches.labels("applied")

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        if method not in LABELLED_METHODS:
            method = "other"
        key = (method, route, status)
        children = self._request_children.get(key)
        if children is None:
            labels = (method, route, str(status))
            children = self._request_children[key] = (
                self.requests.labels(*labels),
                self.latency.labels(*labels),
            )
        children[0].inc()
        children[1].observe(seconds)
        if route == BATCH_ROUTE and method == "POST":
            self.recent.add_latency(seconds)

    def observe_batch(self, epochs: int, seconds: float) -> None:
        self._applied.inc()
        self.epochs.inc(epochs)
        self.recent.add_batch(epochs)
        self.pipeline_batch.observe(seconds)
        if epochs:
            self.filter_step.observe(seconds / epochs)

    def render(self, active_sessions: int) -> bytes:
        self.active_sessions.set(active_sessions)
        return generate_latest(self.registry)
