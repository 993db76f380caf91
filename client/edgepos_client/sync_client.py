"""The blocking client: :class:`EdgeposClient`."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Self

import httpx

from edgepos_client import _protocol as protocol
from edgepos_client._protocol import Call, MeasurementLike, NavigationLike, RetryPolicy, RsuLike, Session
from edgepos_client.models import (
    EphemeridesSummary,
    Fix,
    FixEvent,
    InitialState,
    PipelineInfo,
    Revocation,
    Rsu,
    SessionInfo,
    SessionPage,
    StreamNotice,
    Track,
    Vehicle,
    VehicleImport,
    VehicleKey,
    VehiclePage,
)

if TYPE_CHECKING:
    from edgepos_client.websocket import BatchSocket


class _Retry(Exception):
    """A 503 on opening the stream: try again."""


class EdgeposClient:
    """Blocking client of an edgepos server (API v1).

    ``admin_key`` is the bearer of admin calls (RSU writes, the vehicle registry, sessions opened by
    id). A vehicle gives its own credential instead, ``vehicle_key`` (its key from the registry) or
    ``vehicle_token`` (a fleet-signed token), which opens sessions for that vehicle only; without one,
    :meth:`create_session` uses the admin key. Session calls use the :class:`Session` handle's own
    token. ``timeout`` is per attempt (s); ``retries`` bounds further attempts after a connection
    error, a timeout or a 503, waiting ``backoff * 2**n`` s. Use as a context manager, or call
    :meth:`close`.
    """

    def __init__(
        self,
        base_url: str,
        admin_key: str | None = None,
        *,
        vehicle_key: str | None = None,
        vehicle_token: str | None = None,
        timeout: float = 10.0,
        retries: int = 3,
        backoff: float = 0.2,
        transport: httpx.BaseTransport | None = None,
        limits: httpx.Limits | None = None,
    ) -> None:
        self.policy = RetryPolicy(retries=retries, backoff=backoff)
        self._calls = protocol.Calls(admin_key, protocol.vehicle_credential(vehicle_key, vehicle_token))
        options: dict[str, Any] = {"base_url": base_url, "timeout": timeout, "transport": transport}
        if limits is not None:
            options["limits"] = limits
        self._http = httpx.Client(**options)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _send(self, call: Call) -> httpx.Response:
        attempt = 0
        while True:
            try:
                response = self._http.request(
                    call.method, call.path, content=call.body, headers=call.headers()
                )
            except httpx.TransportError as error:
                if not self.policy.may_retry_error(call, error, attempt):
                    raise protocol.transport_failure(call, error, attempt + 1) from error
            else:
                if not self.policy.may_retry_status(call, response.status_code, attempt):
                    return protocol.check(response)
            time.sleep(self.policy.delay(attempt))
            attempt += 1

    # RSU registry
    def put_rsus(self, rsus: Iterable[RsuLike]) -> int:
        """Insert or replace RSUs by id (admin); returns how many were written."""
        return protocol.parse_upserted(self._send(self._calls.put_rsus(rsus)))

    def list_rsus(self, session: Session | None = None) -> list[Rsu]:
        """Every RSU (with the admin key, or ``session``'s token)."""
        return protocol.parse_rsus(self._send(self._calls.list_rsus(session)))

    def get_rsu(self, rsu_id: str, session: Session | None = None) -> Rsu:
        return protocol.parse_rsu(self._send(self._calls.get_rsu(rsu_id, session)))

    def put_rsu(self, rsu: RsuLike) -> Rsu:
        """Insert or replace one RSU (admin)."""
        return protocol.parse_rsu(self._send(self._calls.put_rsu(rsu)))

    def delete_rsu(self, rsu_id: str) -> None:
        self._send(self._calls.delete_rsu(rsu_id))

    # broadcast ephemerides
    def put_ephemerides(self, navigation: NavigationLike) -> EphemeridesSummary:
        """Load the site's RINEX 3 navigation file (admin): its text, bytes, or a path to it. Returns what
        the server loaded; a malformed file raises InvalidRequest naming the line."""
        return protocol.parse_ephemerides(self._send(self._calls.put_ephemerides(navigation)))

    def get_ephemerides(self, session: Session | None = None) -> EphemeridesSummary:
        """The loaded file's summary (admin key, or ``session``'s token); NotFound when none is loaded."""
        return protocol.parse_ephemerides(self._send(self._calls.get_ephemerides(session)))

    def delete_ephemerides(self) -> None:
        """Unload the navigation file (admin)."""
        self._send(self._calls.delete_ephemerides())

    # pipelines
    def pipelines(self) -> list[PipelineInfo]:
        """Every pipeline with its options (defaults, bounds) and measurement types."""
        return protocol.parse_pipelines(self._send(self._calls.pipelines()))

    # vehicle registry (admin)
    def register_vehicle(self, vehicle_id: str) -> VehicleKey:
        """Register a vehicle and return its key, shown this once (Conflict if already registered:
        :meth:`rotate_vehicle_key` issues a new key). Not retried once the request may have arrived."""
        return protocol.parse_vehicle_key(self._send(self._calls.register_vehicle(vehicle_id)))

    def import_vehicle_chunks(self, vehicle_ids: Iterable[str]) -> Iterator[VehicleImport]:
        """Register many vehicles, yielding each chunk's result (with its keys) as soon as the server
        registered it. Every id is checked and duplicates refused (ValueError) before anything is sent;
        each chunk of at most 5,000 ids is one atomic write, so if one fails the chunks yielded before it
        stay registered: save their keys as they come (``edgepos vehicles import`` does)."""
        for chunk in protocol.vehicle_chunks(vehicle_ids):
            yield protocol.parse_vehicle_import(self._send(self._calls.import_vehicles(chunk)))

    def import_vehicles(self, vehicle_ids: Iterable[str]) -> VehicleImport:
        """Register many vehicles (in chunks of 5,000): those registered now with their keys, shown this
        once, and the ids registered before, left unchanged. See :meth:`import_vehicle_chunks` for
        keeping the keys of the chunks sent before a failure."""
        return protocol.merge_imports(self.import_vehicle_chunks(vehicle_ids))

    def list_vehicles(self, after: str | None = None, limit: int = 100) -> VehiclePage:
        """One page of registered vehicles in id order, after the id ``after`` (1 <= limit <= 1000)."""
        return protocol.parse_vehicle_page(self._send(self._calls.list_vehicles(after, limit)))

    def iter_vehicles(self, limit: int = 100) -> Iterator[Vehicle]:
        """Every registered vehicle in id order, fetching pages of ``limit`` as they are needed."""
        after: str | None = None
        while True:
            page = self.list_vehicles(after, limit)
            yield from page.vehicles
            if page.next_after is None:
                return
            after = page.next_after

    def get_vehicle(self, vehicle_id: str) -> Vehicle:
        """A registered vehicle (NotFound if it is not)."""
        return protocol.parse_vehicle(self._send(self._calls.get_vehicle(vehicle_id)))

    def revoke_vehicle(self, vehicle_id: str) -> Revocation:
        """Remove a vehicle from the registry: its key opens nothing and its live session ends."""
        return protocol.parse_revocation(self._send(self._calls.revoke_vehicle(vehicle_id)))

    def rotate_vehicle_key(self, vehicle_id: str) -> VehicleKey:
        """Issue the vehicle a new key, shown this once; the old key opens nothing from now on (its
        live session keeps running). Not retried once the request may have arrived."""
        return protocol.parse_vehicle_key(self._send(self._calls.rotate_vehicle_key(vehicle_id)))

    # sessions
    def create_session(
        self,
        vehicle_id: str,
        pipeline: str = "rsu_imu",
        *,
        options: Mapping[str, Any] | None = None,
        initial_state: InitialState | Mapping[str, Any] | None = None,
    ) -> Session:
        """Open a session (with the vehicle credential if given, else the admin key); the returned
        handle carries its id and token and tracks seq. A vehicle has one live session: this one
        supersedes the vehicle's previous session (named by ``superseded``), whose token then gets
        :class:`Superseded`."""
        call = self._calls.create_session(vehicle_id, pipeline, options, initial_state)
        return protocol.parse_session(self._send(call))

    def list_sessions(
        self,
        after: str | None = None,
        limit: int = 100,
        *,
        pipeline: str | None = None,
        vehicle_id: str | None = None,
    ) -> SessionPage:
        """One page of live sessions in session-id order (admin), optionally of one pipeline or vehicle."""
        call = self._calls.list_sessions(after, limit, pipeline, vehicle_id)
        return protocol.parse_session_page(self._send(call))

    def get_session(self, session: Session | str) -> SessionInfo:
        return protocol.parse_session_info(self._send(self._calls.get_session(session)))

    def track(self, session: Session | str, *, smoothed: bool = False) -> Track:
        """The estimates of the session's lag window (its last ``max_delay_s`` seconds), oldest first;
        ``smoothed``: smoothed over the window (pipelines that have a smoother)."""
        return protocol.parse_track(self._send(self._calls.track(session, smoothed)))

    def delete_session(self, session: Session | str) -> None:
        self._send(self._calls.delete_session(session))

    def send_batch(
        self,
        session: Session | str,
        measurements: Sequence[MeasurementLike],
        seq: int | None = None,
        *,
        include_state: bool = False,
    ) -> list[Fix]:
        """Send one batch and return one fix per epoch, in time order.

        ``seq`` defaults to the handle's last seq + 1. After a timeout, a broken connection or a
        503 the identical bytes are sent again with the same seq; the server applies it once."""
        number = protocol.next_seq(session, seq)
        call = self._calls.batch(session, measurements, number, include_state)
        return protocol.batch_fixes(session, number, self._send(call))

    def websocket(
        self, session: Session | str, *, timeout: float | None = None, compression: bool = False
    ) -> BatchSocket:
        """The session's batches over one WebSocket (``/v1/sessions/{id}/ws``), for a vehicle that keeps a
        link open: its ``send_batch`` sends the same bytes as :meth:`send_batch`, returns the same fixes
        and raises the same errors, with one batch in flight. The link opens with the first batch and is
        opened again (the batch resent with its seq) after it breaks, within the retry policy; close it
        (or use it as a context manager) when done. ``timeout`` (s) bounds each answer, by default the
        client's; ``compression`` turns on permessage-deflate (fewer bytes on a slow link, more CPU).
        Needs a real server (the WebSocket does not go through an httpx ``transport``) and the
        ``websockets`` package: ``pip install 'edgepos-client[websocket]'``."""
        from edgepos_client.websocket import BatchSocket, SocketTarget

        wait = timeout if timeout is not None else self._http.timeout.read
        target = SocketTarget.of(
            self._http.base_url,
            self._calls,
            session,
            self.policy,
            10.0 if wait is None else wait,
            compression,
        )
        return BatchSocket(target, session, self._calls)

    def stream_fixes(
        self,
        session: Session | None = None,
        *,
        session_id: str | None = None,
        pipelines: Iterable[str] | None = None,
        vehicle_ids: Iterable[str] | None = None,
        max_rate_hz: float | None = None,
        last_event_id: str | None = None,
        reconnect: bool = True,
        read_timeout: float = 60.0,
    ) -> Iterator[FixEvent | StreamNotice]:
        """The fix stream (``GET /v1/stream/fixes``): each applied fix as a :class:`FixEvent`, as it is
        applied, and the server's :class:`StreamNotice` events (``missed``: fixes lost to the buffer when
        resuming; ``end``: the server ended the stream).

        With a ``session`` handle, that session's fixes (its token); else every session's (the admin key),
        narrowed by ``session_id``, ``pipelines``, ``vehicle_ids``; ``max_rate_hz`` decimates per vehicle.
        ``last_event_id`` resumes after that event. With ``reconnect`` a dropped connection, a 503 or an
        ``end`` for a slow consumer is followed by a new connection that resumes after the last fix
        received (``Last-Event-ID``), after up to ``retries`` consecutive failures; ``read_timeout`` (s)
        must exceed the server's ping interval (15 s). Stop by breaking out of the loop."""
        request = protocol.stream_request(
            self._calls, session, session_id, pipelines, vehicle_ids, max_rate_hz
        )
        timeout = httpx.Timeout(
            self._http.timeout.connect, read=read_timeout, write=read_timeout, pool=read_timeout
        )
        failures = 0
        while True:
            try:
                with self._http.stream(
                    "GET", request.path, headers=request.headers(last_event_id), timeout=timeout
                ) as response:
                    if not response.is_success:
                        response.read()
                        if not (reconnect and response.status_code == 503 and failures < self.policy.retries):
                            protocol.check(response)
                        raise _Retry
                    failures = 0
                    parser = protocol.SseParser()
                    for line in response.iter_lines():
                        parsed = parser.feed(line)
                        item = None if parsed is None else protocol.stream_item(*parsed)
                        if item is None:
                            continue
                        if isinstance(item, FixEvent):
                            last_event_id = item.id
                        yield item
                        if isinstance(item, StreamNotice) and item.event == "end":
                            if not reconnect or item.reason != "slow_consumer":
                                return
                            break
                if not reconnect:
                    return
            except (httpx.TransportError, _Retry) as error:
                if not reconnect or failures >= self.policy.retries:
                    if isinstance(error, httpx.TransportError):
                        raise protocol.transport_failure(
                            protocol.Call("GET", request.path), error, failures + 1
                        ) from error
                    raise
                failures += 1
            time.sleep(self.policy.delay(max(0, failures - 1)))
