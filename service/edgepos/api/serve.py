"""``edgepos serve``: run the service under uvicorn with the app factory.

Settings come from ``EDGEPOS_*``; --host, --port, --workers and --log-level override them. The
admin key is settled here, before workers start, so that every worker uses the same one.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import TextIO

from pydantic import ValidationError

from edgepos.api.logs import configure_logging
from edgepos.api.settings import Settings, ensure_admin_key

APP_FACTORY = "edgepos.api.app:create_app"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--host", default=None, help="address to listen on (default: $EDGEPOS_HOST or 127.0.0.1)"
    )
    parser.add_argument("--port", type=int, default=None, help="TCP port (default: $EDGEPOS_PORT or 8000)")
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="worker processes (default: $EDGEPOS_WORKERS or 1); more than 1 needs a shared store, EDGEPOS_STORE=redis://... or sqlite:///path.db",
    )
    parser.add_argument(
        "--lab",
        action="store_true",
        default=None,
        help="declare this a lab instance: the only way EDGEPOS_AUTH=off, or EDGEPOS_VEHICLE_AUTH=open on a "
        "non-loopback address, is accepted (default: $EDGEPOS_LAB or false)",
    )
    parser.add_argument(
        "--log-level",
        default=None,
        choices=["critical", "error", "warning", "info", "debug"],
        help="log level (default: $EDGEPOS_LOG_LEVEL or info)",
    )


def _settings(args: argparse.Namespace) -> Settings:
    overrides = {
        key: value
        for key, value in (
            ("host", args.host),
            ("port", args.port),
            ("workers", args.workers),
            ("log_level", args.log_level),
            ("lab", getattr(args, "lab", None)),
        )
        if value is not None
    }
    return Settings(**overrides)


KEEP_ALIVE_S = 75
"""Seconds an idle keep-alive connection stays open."""

WS_PING_INTERVAL_S = 20.0
"""Seconds between the server's protocol pings on a batch WebSocket: they keep NAT and proxy mappings of a
quiet link alive and notice a vehicle that vanished without closing."""

WS_PING_TIMEOUT_S = 20.0
"""Seconds a ping may go unanswered before the server drops the link."""

GRACEFUL_SHUTDOWN_S = 10
"""On SIGTERM, how long a worker waits for its requests in progress before cancelling them. A fix stream
(GET /v1/stream/fixes) never ends by itself: without a bound uvicorn would wait for every consumer to
leave. Batches take milliseconds; consumers reconnect elsewhere with Last-Event-ID."""


def warm_up_kernels(stream: TextIO) -> float:
    """Compile the filter kernels (or load them from numba's on-disk cache) before the port opens, and
    say so on ``stream`` when that compiles: the first start on a machine takes tens of seconds with
    the port closed, which looks like a hang. One line, its end written when done. The workers then
    load the kernels from the cache (or, in this process with one worker, have them already)."""
    from edgepos.core.compiled import (
        compiled_enabled,
        kernel_cache_dir,
        kernels_cached,
        kernels_compiled,
        warm_up,
    )

    if not compiled_enabled():
        return 0.0
    cold = not kernels_cached()
    if cold:
        cache = kernel_cache_dir()
        where = (
            f"numba's cache in {cache}, once"
            if cache is not None
            else "no writable numba cache directory: every start compiles; set NUMBA_CACHE_DIR"
        )
        print(
            f"edgepos serve: compiling the filter kernels the first time ({where}; tens of seconds, "
            "the port opens after) ...",
            end="",
            file=stream,
            flush=True,
        )
    seconds = warm_up()
    if cold:
        print(f" done in {seconds:.1f} s", file=stream, flush=True)
    elif kernels_compiled():  # the cache was there but stale (another CPU, changed sources)
        print(
            f"edgepos serve: compiled the filter kernels again (numba's cache was stale) in {seconds:.1f} s",
            file=stream,
            flush=True,
        )
    return seconds


def run(args: argparse.Namespace) -> int:
    import uvicorn

    try:
        settings = _settings(args)
    except ValidationError as error:
        print(f"edgepos serve: invalid configuration:\n{error}", file=sys.stderr)
        return 2
    if settings.workers > 1 and settings.store == "memory":
        print(
            f"edgepos serve: --workers {settings.workers} needs a store shared by the workers; with the "
            "in-process store each worker would hold a different set of sessions. Set "
            "EDGEPOS_STORE=redis://host:6379/0 or sqlite:///path/to/edgepos.db (or run one worker).",
            file=sys.stderr,
        )
        return 2
    if settings.vehicle_auth == "jwt" and settings.vehicle_jwks is not None:
        from edgepos.api.vehicle_jwt import JwksError, load_vehicle_jwks

        try:
            load_vehicle_jwks(settings.vehicle_jwks)
        except JwksError as error:
            print(f"edgepos serve: EDGEPOS_VEHICLE_JWKS: {error}", file=sys.stderr)
            return 2
    if settings.vehicle_auth == "open" and settings.auth_enabled:
        print(
            "edgepos serve: EDGEPOS_VEHICLE_AUTH=open: anyone who reaches this port can open a session as any "
            "vehicle (allowed on loopback or in a lab only).",
            file=sys.stderr,
        )
    if not settings.auth_enabled:
        print(
            "edgepos serve: LAB MODE, AUTHENTICATION IS OFF: anyone who reaches this port can read and write "
            "every session and the RSU map. Never point real vehicles at this instance.",
            file=sys.stderr,
        )
    settings = ensure_admin_key(settings)
    admin_key = settings.admin_key.get_secret_value() if settings.admin_key is not None else ""
    # The workers build their apps from the environment: hand them the settled values.
    os.environ["EDGEPOS_ADMIN_KEY"] = admin_key
    os.environ["EDGEPOS_LOG_LEVEL"] = settings.log_level
    os.environ["EDGEPOS_LAB"] = "true" if settings.lab else "false"
    configure_logging(settings.log_level, secrets=[admin_key])
    warm_up_kernels(sys.stderr)
    uvicorn.run(
        APP_FACTORY,
        factory=True,
        host=settings.host,
        port=settings.port,
        workers=settings.workers,
        log_config=None,
        log_level=settings.log_level,
        access_log=False,
        server_header=False,
        # Longer than any client's idle-connection expiry (httpx: 5 s), so that a vehicle never sends
        # a batch on a connection the server is closing at that moment (a reset, not an answer).
        timeout_keep_alive=KEEP_ALIVE_S,
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
        # The batch WebSocket (/v1/sessions/{id}/ws): the websockets library refuses a frame over the body
        # limit (close 1009) before reading it, so a frame is never buffered past EDGEPOS_MAX_BODY_BYTES.
        ws="websockets-sansio",
        ws_max_size=settings.max_body_bytes,
        ws_ping_interval=WS_PING_INTERVAL_S,
        ws_ping_timeout=WS_PING_TIMEOUT_S,
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m edgepos.api.serve``: the same as ``edgepos serve``."""
    parser = argparse.ArgumentParser(prog="edgepos serve", description="run the edge positioning service")
    configure(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
