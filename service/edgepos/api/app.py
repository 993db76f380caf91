"""The FastAPI application factory: ``create_app(settings)``.

uvicorn calls ``create_app()`` (``--factory``) in each worker, which then reads its settings from
the ``EDGEPOS_*`` environment. Tests pass settings (and may pass a store or pipelines) directly.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
from collections.abc import AsyncIterator, Mapping
from importlib import resources
from typing import Any

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import RedirectResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles

from edgepos import __version__
from edgepos.api.context import AppContext
from edgepos.api.direct_path import DirectPathMiddleware
from edgepos.api.errors import install_error_handlers
from edgepos.api.location.notifier import LocationNotifier
from edgepos.api.logs import configure_logging
from edgepos.api.metrics import Metrics
from edgepos.api.middleware import (
    Admission,
    AdmissionMiddleware,
    BodyLimitMiddleware,
    RequestContextMiddleware,
)
from edgepos.api.routes import (
    base_stations,
    docs,
    ephemerides,
    health,
    location,
    operator_map,
    rsus,
    sessions,
    status,
    streams,
    vehicles,
    zones,
)
from edgepos.api.routes import pipelines as pipeline_routes
from edgepos.api.settings import Settings, ensure_admin_key
from edgepos.api.vehicle_jwt import load_vehicle_jwks
from edgepos.core.compiled import warm_up as warm_up_kernels
from edgepos.pipelines.base import Pipeline, Rsu
from edgepos.pipelines.gnss_integrity import warm_up_gnss_tables
from edgepos.pipelines.integrity import warm_up_tables
from edgepos.store import SessionStore, open_store
from edgepos.store.base import StoreUnavailable

logger = logging.getLogger("edgepos.api")

YOUNG_GC_THRESHOLD = 10_000
"""Net allocations of container objects between two young-generation collections while the app serves
(Python's default: 700). A 20-epoch batch holds more than 700 new objects at its peak (its measurements,
observations, fixes and their JSON), so at the default nearly every batch ran a young collection (median
100 us), every tenth a middle one and every 150th a full one (5-6 ms): 150-157 us of collection per batch,
6-7 % of the worker's CPU, and not one object collected in 3,000 batches (they die by reference count).
At 10,000, two young collections in 3,000 batches (2.8 ms each). Objects that do not go away, cyclic
garbage among them, still trigger a collection every 10,000, so little can pile up (docs/benchmarks.md,
"svcwrite: the worker's CPU outside the filter, round two")."""

DESCRIPTION = """\
Edge positioning service: vehicles open a session, send batches of measurements (roadside-unit (RSU)
range/bearing and gyro; GNSS pseudoranges and reduced inertial samples) and get one position fix per
measurement epoch. The site's broadcast ephemerides are loaded once with PUT /v1/ephemerides.

Conventions: SI units and radians everywhere; positions in the site-local east-north plane in metres
(x east, y north); angles counter-clockwise from east. Authentication is `Authorization: Bearer ...`
with the admin key (the registries, any session), a vehicle's credential (its key from
POST /v1/vehicles, or a fleet-signed token: opens sessions for that vehicle only), or a session's
token (that session only). A vehicle has one live session: opening another supersedes the old one.
Every error has the body `{"error": {"code", "message", "problems": [{"index", "field", "reason"}]}}`.

Request bodies are strict JSON: an integer field takes an integer literal (41, not 41.0, although JSON
Schema counts 41.0 as an integer) and a number is never a string. Some rules depend on state or on
other requests and are stated in the descriptions, not the schema: the batch's seq and known RSU ids,
a session's initial speed within its max_speed_mps option, base observations needing loaded
ephemerides, uploaded files being RINEX or RTCM, ids unique within one request, a body id equal to
the path's. The body limits (EDGEPOS_MAX_BODY_BYTES and the upload limits) answer 413.

The ETSI GS MEC 013 location adapter under /location/v3 is the one exception: it follows that
specification, so its angles are degrees, its speeds km/h and its errors RFC 7807 problem details
(application/problem+json). It needs the admin key or the read key (EDGEPOS_READ_KEY) and the site
origin (EDGEPOS_ORIGIN_LAT/LON); its zones are defined by the operator with /v1/zones.
"""


def operation_id(route: APIRoute) -> str:
    """An operation's OpenAPI id: its handler's name (``create_session``, ``post_batch``), short and stable
    for generated clients; the handler names are unique across the API (tested)."""
    return route.name


def _demo_rsus() -> list[Rsu]:
    """The RSU map of the paper's scenario (the simulator's layout)."""
    from edgepos.sim.scenarios import rsu_imu_paper_scenario

    return list(rsu_imu_paper_scenario().rsus)


async def _expire_periodically(store: SessionStore, period_s: float) -> None:
    while True:
        await asyncio.sleep(period_s)
        try:
            removed = await store.expire()
        except Exception:  # keep sweeping: a transient store error must not end the task
            logger.exception("session expiry failed", extra={"event": "expiry_failed"})
            continue
        if removed:
            logger.info("sessions expired", extra={"event": "sessions_expired", "count": removed})


def add_pipeline_enum(document: dict[str, Any], names: list[str]) -> None:
    """State in the schema which pipeline names this server accepts: the registered ones (a new
    pipeline in the registry appears here by itself). The model keeps its name pattern, so the
    refusal of any other name stays the route's documented 422."""
    field = document["components"]["schemas"]["SessionCreate"]["properties"]["pipeline"]
    field["enum"] = names
    field["description"] = f"{field['description']} One of: {', '.join(names)}."


def create_app(
    settings: Settings | None = None,
    *,
    store: SessionStore | None = None,
    pipelines: Mapping[str, Pipeline] | None = None,
) -> FastAPI:
    """A ready-to-serve app. Without ``settings`` they come from the environment; without an admin
    key one is generated (printed once to stderr and written to ``admin_key_file``)."""
    settings = ensure_admin_key(settings if settings is not None else Settings())
    admin_key = settings.admin_key.get_secret_value() if settings.admin_key is not None else ""
    read_key = settings.read_key.get_secret_value() if settings.read_key is not None else None
    configure_logging(settings.log_level, secrets=[admin_key] + ([read_key] if read_key else []))
    if pipelines is None:
        from edgepos.pipelines.registry import PIPELINES

        pipelines = PIPELINES
    vehicle_keys = None
    if settings.vehicle_auth == "jwt" and settings.vehicle_jwks is not None:
        vehicle_keys = load_vehicle_jwks(settings.vehicle_jwks)  # JwksError stops the start, naming the file
    context = AppContext(
        vehicle_keys=vehicle_keys,
        settings=settings,
        store=store
        if store is not None
        else open_store(
            settings.store,
            settings.session_ttl_s,
            wait_replicas=settings.redis_wait_replicas,
            wait_timeout_ms=settings.redis_wait_timeout_ms,
        ),
        pipelines=dict(pipelines),
        metrics=Metrics(),
        origin=settings.origin,
        admin_key_hash=AppContext.hash_admin_key(admin_key),
        read_key_hash=None if read_key is None else AppContext.hash_admin_key(read_key),
    )
    context.admission = Admission(settings.max_inflight, settings.queue_timeout_s, context.metrics)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if settings.demo_rsus:
            try:
                count = await context.store.upsert_rsus(_demo_rsus())
                logger.info("demo RSU map loaded", extra={"event": "demo_rsus", "count": count})
            except StoreUnavailable:  # start anyway: /readyz reports the store until it answers
                logger.warning(
                    "demo RSU map not loaded: the store does not answer", extra={"event": "demo_rsus"}
                )
        # Compile the filter kernels (or load them from numba's cache) before the first request.
        seconds = await context.run_filter(warm_up_kernels)
        logger.info("filter kernels ready", extra={"event": "warm_up", "seconds": round(seconds, 3)})
        # The integrity monitor's tables by quadrature (about 30 ms per number of sub-filters): now, not
        # in the filter thread while the first vehicles wait behind it.
        await context.run_filter(warm_up_tables)
        # ... and gnss_tight's RAIM tables, one per hypothesis count (about 50 ms each, 25 counts).
        await context.run_filter(warm_up_gnss_tables)
        # The ~150k objects of the imported libraries and compiled kernels live as long as the process:
        # move them out of the collector's sight, or every full collection walks them all and stalls every
        # request for 50-100 ms (measured: the p99 latency at 100 vehicles x 20 Hz was those pauses).
        gc.collect()
        gc.freeze()
        thresholds = gc.get_threshold()
        gc.set_threshold(YOUNG_GC_THRESHOLD, *thresholds[1:])
        sweep_period = min(60.0, max(0.5, settings.session_ttl_s / 4.0))
        sweeper = asyncio.create_task(_expire_periodically(context.store, sweep_period))
        notifier = asyncio.create_task(LocationNotifier(context.store, settings, context.origin).run())
        if not settings.auth_enabled:
            logger.warning(
                "LAB MODE: authentication is off; every request has admin rights", extra={"event": "auth_off"}
            )
        logger.info("edgepos ready", extra={"event": "startup", "store": settings.store.split(":", 1)[0]})
        try:
            yield
        finally:
            for task in (sweeper, notifier):
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            await context.close_streams()
            await context.store.close()
            context.stop_filter_thread()
            gc.set_threshold(*thresholds)

    app = FastAPI(
        title="edgepos",
        version=__version__,
        description=DESCRIPTION,
        docs_url=None,
        redoc_url=None,
        lifespan=lifespan,
        generate_unique_id_function=operation_id,
    )
    app.state.context = context
    install_error_handlers(app)
    allowed_methods: dict[str, set[str]] = {}
    routers = (
        rsus.router,
        ephemerides.router,
        base_stations.router,
        pipeline_routes.router,
        sessions.router,
        sessions.batch_router,
        streams.router,
        vehicles.router,
        zones.router,
        location.router,
        health.router,
        status.router,
        docs.router,
        operator_map.router,
    )
    # ``routers`` is the API's order in its documentation. Requests are matched route by route, so the batch
    # route, which takes nearly every request, goes first, then the rest of the sessions router (no other
    # router's paths start with /v1/sessions, and no other sessions route's path matches a batch's, so no
    # request is matched differently): 5-6 us less CPU per epoch of a 20-epoch batch than behind the four
    # routers and five routes before it (docs/benchmarks.md, "The batch request's HTTP path").
    first = (sessions.batch_router, sessions.router)
    for router in (*first, *(router for router in routers if router not in first)):
        app.include_router(router)
    documented: dict[str, int] = {}
    for router in routers:
        for route in router.routes:
            if isinstance(route, APIRoute):
                documented.setdefault(route.path_format, len(documented))
                allowed_methods.setdefault(route.path, set()).update(route.methods or ())
    app.state.allowed_methods = allowed_methods
    default_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            document = default_openapi()
            document["paths"] = dict(sorted(document["paths"].items(), key=lambda item: documented[item[0]]))
            streams.add_event_schemas(document)
            location.add_problem_schema(document)
            add_pipeline_enum(document, sorted(context.pipelines))
        return app.openapi_schema or default_openapi()

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to extend the schema

    @app.get("/", include_in_schema=False)
    async def root() -> RedirectResponse:
        """People who open the bare address land on the API documentation (which links the map)."""
        return RedirectResponse("/docs", status_code=307)

    static_dir = resources.files("edgepos.api") / "static"
    app.mount(docs.STATIC_PREFIX, StaticFiles(directory=str(static_dir)), name="static")

    # Innermost: the batch route's valid requests go to its direct handler past FastAPI's routing. It is the
    # first route the router tries (above), so no other route could have taken them.
    direct_routes = [route for route in sessions.batch_router.routes if isinstance(route, APIRoute)]
    app.add_middleware(DirectPathMiddleware, fastapi_app=app, routes=direct_routes)
    app.add_middleware(
        BodyLimitMiddleware,
        max_bytes=settings.max_body_bytes,
        path_limits={
            ephemerides.PATH: (settings.max_ephemerides_bytes, "EDGEPOS_MAX_EPHEMERIDES_BYTES"),
            f"{base_stations.PATH}/*": (
                settings.max_base_observations_bytes,
                "EDGEPOS_MAX_BASE_OBSERVATIONS_BYTES",
            ),
        },
    )
    if settings.cors_origin_list:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origin_list,
            allow_methods=["GET", "POST", "PUT", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "X-Request-ID"],
            expose_headers=["X-Request-ID"],
        )
    app.add_middleware(AdmissionMiddleware, admission=context.admission)
    app.add_middleware(RequestContextMiddleware, metrics=context.metrics)
    return app
