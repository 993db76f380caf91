"""What the sync and async clients share: the session handle, the retry policy, and each call's
request (method, path, body bytes, credential, what may be retried) and answer parsing.

Keeping this free of I/O lets both clients be thin loops around ``httpx`` that cannot drift apart.
"""

from __future__ import annotations

import json
import math
import os
import random
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, cast
from urllib.parse import quote, urlencode

import httpx

from edgepos_client.errors import EdgeposError, TransportError, error_from_response
from edgepos_client.models import (
    MEASUREMENTS,
    VEHICLE_ID_PATTERN,
    BatchResult,
    EphemeridesSummary,
    Fix,
    FixEvent,
    GnssFixMeasurement,
    GyroMeasurement,
    InitialState,
    Measurement,
    OdometerMeasurement,
    PipelineInfo,
    PseudorangeMeasurement,
    Revocation,
    RissMeasurement,
    Rsu,
    RsuMeasurement,
    RsuRangeMeasurement,
    SessionCreated,
    SessionInfo,
    SessionPage,
    StreamNotice,
    Track,
    V2vRangeMeasurement,
    Vehicle,
    VehicleImport,
    VehicleKey,
    VehiclePage,
)

_MEASUREMENT_MODELS = (
    RsuMeasurement,
    GyroMeasurement,
    RsuRangeMeasurement,
    GnssFixMeasurement,
    OdometerMeasurement,
    V2vRangeMeasurement,
    PseudorangeMeasurement,
    RissMeasurement,
)
MeasurementLike = (
    RsuMeasurement
    | GyroMeasurement
    | RsuRangeMeasurement
    | GnssFixMeasurement
    | OdometerMeasurement
    | V2vRangeMeasurement
    | PseudorangeMeasurement
    | RissMeasurement
    | Mapping[str, Any]
)
NavigationLike = str | bytes | os.PathLike[str]
"""A RINEX navigation file: its text, its bytes, or a path to read it from."""
RsuLike = Rsu | Mapping[str, Any]

MAX_VEHICLES_PER_IMPORT = 5_000
"""The server registers at most this many vehicles per request; larger imports are sent in chunks."""
_VEHICLE_ID = re.compile(VEHICLE_ID_PATTERN)


@dataclass
class Session:
    """A handle on one server session: its id, its bearer token, and the last seq it sent.

    ``send_batch`` without an explicit seq sends ``last_seq + 1`` and records it once the server
    accepted it. To resume a session in another process, build one from the stored id, token and
    last seq.
    """

    session_id: str
    token: str = field(repr=False)
    vehicle_id: str = ""
    pipeline: str = ""
    options: dict[str, Any] = field(default_factory=dict)
    created_at: float = 0.0
    last_seq: int = 0
    superseded: str | None = None
    """The vehicle's previous live session, which opening this one replaced (None if it had none)."""

    @classmethod
    def from_created(cls, created: SessionCreated) -> Session:
        return cls(
            session_id=created.session_id,
            token=created.token,
            vehicle_id=created.vehicle_id,
            pipeline=created.pipeline,
            options=dict(created.options),
            created_at=created.created_at,
            superseded=created.superseded,
        )


class Retry(Enum):
    """What a failed attempt of a call may be retried after."""

    NEVER = "never"
    CONNECT = "connect"
    """Only when the request surely never reached the server (refused or timed out connecting)."""
    ALWAYS = "always"
    """Any transport error or timeout, and 503: the call is idempotent (or, for batches, made so by seq)."""


_NOT_SENT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout)


@dataclass(frozen=True)
class RetryPolicy:
    """At most ``retries`` further attempts, waiting ``backoff * 2**n`` seconds (capped, with jitter)."""

    retries: int = 3
    backoff: float = 0.2
    max_backoff: float = 5.0

    def __post_init__(self) -> None:
        if self.retries < 0 or self.backoff < 0 or self.max_backoff < 0:
            raise ValueError("retries, backoff and max_backoff must be >= 0")

    def delay(self, attempt: int) -> float:
        """Seconds to wait before retry number ``attempt`` (0-based): exponential, 50-100 % jitter."""
        return min(self.max_backoff, self.backoff * 2.0**attempt) * (0.5 + 0.5 * random.random())

    def may_retry_error(self, call: Call, error: httpx.TransportError, attempt: int) -> bool:
        if attempt >= self.retries or call.retry is Retry.NEVER:
            return False
        return call.retry is Retry.ALWAYS or isinstance(error, _NOT_SENT)

    def may_retry_status(self, call: Call, status: int, attempt: int) -> bool:
        return attempt < self.retries and call.retry is Retry.ALWAYS and status == 503


@dataclass(frozen=True)
class Call:
    """One API request, fully encoded, so every attempt sends exactly the same bytes."""

    method: str
    path: str
    body: bytes | None = None
    credential: str | None = None
    retry: Retry = Retry.ALWAYS
    content_type: str = "application/json"

    def headers(self) -> dict[str, str]:
        headers = {"Accept": "application/json"}
        if self.body is not None:
            headers["Content-Type"] = self.content_type
        if self.credential:
            headers["Authorization"] = f"Bearer {self.credential}"
        return headers


def transport_failure(call: Call, error: httpx.TransportError, attempts: int) -> TransportError:
    kind = "timeout" if isinstance(error, httpx.TimeoutException) else "connection_error"
    return TransportError(
        kind,
        f"{call.method} {call.path} got no answer after {attempts} attempt(s): {type(error).__name__}: {error}",
    )


def check(response: httpx.Response) -> httpx.Response:
    """The response if it is a success, else the matching :class:`EdgeposError` is raised."""
    if response.is_success:
        return response
    raise error_from_response(response)


def _segment(value: str) -> str:
    return quote(value, safe="")


def _json(value: Any) -> bytes:
    return json.dumps(value, allow_nan=False, separators=(",", ":")).encode()


def _query(path: str, **params: str | int | None) -> str:
    """``path`` with the parameters that are not None as its query string (percent-encoded)."""
    given = {name: value for name, value in params.items() if value is not None}
    return f"{path}?{urlencode(given, quote_via=quote)}" if given else path


def vehicle_id_problem(vehicle_id: object) -> str | None:
    """Why the server would refuse ``vehicle_id`` as a vehicle id, or None if it is valid."""
    if not isinstance(vehicle_id, str):
        return f"a vehicle id must be a string, not {type(vehicle_id).__name__}"
    if not 1 <= len(vehicle_id) <= 128:
        return f"vehicle id {vehicle_id[:40]!r} is {len(vehicle_id)} characters long (1-128 allowed)"
    if _VEHICLE_ID.fullmatch(vehicle_id) is None:
        bad = "".join(sorted({c for c in vehicle_id if _VEHICLE_ID.fullmatch(c) is None}))
        return (
            f"vehicle id {vehicle_id!r} has characters {bad!r}; only letters, digits, space and "
            ". _ : + @ / - are allowed"
        )
    return None


def check_vehicle_ids(vehicle_ids: Iterable[str]) -> list[str]:
    """The ids as a list, after checking each one and that none repeats (ValueError otherwise), so that
    an import in several chunks is refused before anything is sent rather than half-way through."""
    if isinstance(vehicle_ids, str):
        raise TypeError("give an iterable of vehicle ids, not one string (it would be read letter by letter)")
    ids = list(vehicle_ids)
    seen: dict[str, int] = {}
    for number, vehicle_id in enumerate(ids):
        problem = vehicle_id_problem(vehicle_id)
        if problem is not None:
            raise ValueError(f"vehicle_ids[{number}]: {problem}")
        if vehicle_id in seen:
            first = seen[vehicle_id]
            raise ValueError(f"vehicle_ids[{number}]: {vehicle_id!r} is listed twice (first at [{first}])")
        seen[vehicle_id] = number
    return ids


def vehicle_chunks(vehicle_ids: Iterable[str]) -> list[list[str]]:
    """Checked ids in chunks the server takes in one request (one atomic write each)."""
    ids = check_vehicle_ids(vehicle_ids)
    size = MAX_VEHICLES_PER_IMPORT
    return [ids[start : start + size] for start in range(0, len(ids), size)]


def merge_imports(results: Iterable[VehicleImport]) -> VehicleImport:
    """One result from those of several chunks, in the order they were sent."""
    registered: list[VehicleKey] = []
    already: list[str] = []
    for result in results:
        registered.extend(result.registered)
        already.extend(result.already_registered)
    return VehicleImport(registered=registered, already_registered=already)


def vehicle_credential(vehicle_key: str | None, vehicle_token: str | None) -> str | None:
    """The one vehicle credential given (a registry key or a fleet-signed token), or None."""
    if vehicle_key is not None and vehicle_token is not None:
        raise ValueError(
            "give vehicle_key (the key from the vehicle registry) or vehicle_token (a fleet-signed token), "
            "not both: a session is opened with one credential"
        )
    credential = vehicle_key if vehicle_key is not None else vehicle_token
    if credential is not None and not credential.strip():
        raise ValueError("the vehicle credential is empty")
    return credential


def _session_credential(session: Session | str, admin_key: str | None) -> tuple[str, str | None]:
    """(session id, bearer): a handle uses its own token, a bare id needs the admin key."""
    if isinstance(session, Session):
        return session.session_id, session.token
    return session, admin_key


class Calls:
    """Builds each API call; ``admin_key`` is the bearer of admin calls, ``vehicle_credential`` (a
    vehicle's registry key or a fleet-signed token) the bearer of session creation when given."""

    def __init__(self, admin_key: str | None, vehicle_credential: str | None = None) -> None:
        self.admin_key = admin_key
        self.vehicle_credential = vehicle_credential

    # RSU registry
    def put_rsus(self, rsus: Iterable[RsuLike]) -> Call:
        items = [rsu if isinstance(rsu, Rsu) else Rsu.model_validate(rsu) for rsu in rsus]
        body = _json({"rsus": [rsu.model_dump(mode="json") for rsu in items]})
        return Call("PUT", "/v1/rsus", body, self.admin_key)

    def list_rsus(self, session: Session | None) -> Call:
        return Call("GET", "/v1/rsus", credential=session.token if session else self.admin_key)

    def get_rsu(self, rsu_id: str, session: Session | None) -> Call:
        return Call(
            "GET", f"/v1/rsus/{_segment(rsu_id)}", credential=session.token if session else self.admin_key
        )

    def put_rsu(self, rsu: RsuLike) -> Call:
        item = rsu if isinstance(rsu, Rsu) else Rsu.model_validate(rsu)
        body = _json(item.model_dump(mode="json"))
        return Call("PUT", f"/v1/rsus/{_segment(item.id)}", body, self.admin_key)

    def delete_rsu(self, rsu_id: str) -> Call:
        return Call("DELETE", f"/v1/rsus/{_segment(rsu_id)}", credential=self.admin_key, retry=Retry.CONNECT)

    # broadcast ephemerides
    def put_ephemerides(self, navigation: NavigationLike) -> Call:
        """PUT the navigation file (admin); replacing it with the same file is harmless, so it is retried."""
        if isinstance(navigation, os.PathLike):
            body = Path(navigation).read_bytes()
        elif isinstance(navigation, str):
            body = navigation.encode()
        else:
            body = bytes(navigation)
        return Call("PUT", "/v1/ephemerides", body, self.admin_key, content_type="text/plain")

    def get_ephemerides(self, session: Session | None) -> Call:
        return Call("GET", "/v1/ephemerides", credential=session.token if session else self.admin_key)

    def delete_ephemerides(self) -> Call:
        return Call("DELETE", "/v1/ephemerides", credential=self.admin_key, retry=Retry.CONNECT)

    # pipelines
    def pipelines(self) -> Call:
        return Call("GET", "/v1/pipelines", credential=self.admin_key)

    # vehicle registry (admin)
    def register_vehicle(self, vehicle_id: str) -> Call:
        problem = vehicle_id_problem(vehicle_id)
        if problem is not None:
            raise ValueError(problem)
        # not idempotent: a retry after a lost reply would get 409 and lose the issued key
        body = _json({"vehicle_id": vehicle_id})
        return Call("POST", "/v1/vehicles", body, self.admin_key, retry=Retry.CONNECT)

    def import_vehicles(self, chunk: Sequence[str]) -> Call:
        """One chunk (checked ids, at most MAX_VEHICLES_PER_IMPORT) of an import."""
        body = _json({"vehicles": [{"vehicle_id": vehicle_id} for vehicle_id in chunk]})
        return Call("POST", "/v1/vehicles/bulk", body, self.admin_key, retry=Retry.CONNECT)

    def list_vehicles(self, after: str | None, limit: int) -> Call:
        return Call("GET", _query("/v1/vehicles", after=after, limit=limit), credential=self.admin_key)

    def get_vehicle(self, vehicle_id: str) -> Call:
        return Call("GET", f"/v1/vehicles/{_segment(vehicle_id)}", credential=self.admin_key)

    def revoke_vehicle(self, vehicle_id: str) -> Call:
        return Call(
            "DELETE", f"/v1/vehicles/{_segment(vehicle_id)}", credential=self.admin_key, retry=Retry.CONNECT
        )

    def rotate_vehicle_key(self, vehicle_id: str) -> Call:
        # not idempotent: each attempt issues a new key and voids the one before
        return Call(
            "POST", f"/v1/vehicles/{_segment(vehicle_id)}/key", credential=self.admin_key, retry=Retry.CONNECT
        )

    # sessions
    def create_session(
        self,
        vehicle_id: str,
        pipeline: str,
        options: Mapping[str, Any] | None,
        initial_state: InitialState | Mapping[str, Any] | None,
    ) -> Call:
        initial = None
        if initial_state is not None:
            state = (
                initial_state
                if isinstance(initial_state, InitialState)
                else InitialState.model_validate(initial_state)
            )
            initial = state.model_dump(mode="json")
        body = {
            "vehicle_id": vehicle_id,
            "pipeline": pipeline,
            "options": None if options is None else dict(options),
            "initial_state": initial,
        }
        # not idempotent: a retry after a lost reply would open a second session (superseding the first)
        credential = self.vehicle_credential if self.vehicle_credential is not None else self.admin_key
        return Call("POST", "/v1/sessions", _json(body), credential, retry=Retry.CONNECT)

    def list_sessions(
        self, after: str | None, limit: int, pipeline: str | None, vehicle_id: str | None
    ) -> Call:
        path = _query("/v1/sessions", after=after, limit=limit, pipeline=pipeline, vehicle_id=vehicle_id)
        return Call("GET", path, credential=self.admin_key)

    def get_session(self, session: Session | str) -> Call:
        session_id, credential = _session_credential(session, self.admin_key)
        return Call("GET", f"/v1/sessions/{_segment(session_id)}", credential=credential)

    def track(self, session: Session | str, smoothed: bool) -> Call:
        session_id, credential = _session_credential(session, self.admin_key)
        path = _query(f"/v1/sessions/{_segment(session_id)}/track", smoothed="true" if smoothed else "false")
        return Call("GET", path, credential=credential)

    def delete_session(self, session: Session | str) -> Call:
        session_id, credential = _session_credential(session, self.admin_key)
        return Call(
            "DELETE", f"/v1/sessions/{_segment(session_id)}", credential=credential, retry=Retry.CONNECT
        )

    def batch(
        self,
        session: Session | str,
        measurements: Sequence[MeasurementLike],
        seq: int,
        include_state: bool,
    ) -> Call:
        """The batch call; retried with the same seq and bytes, which the server answers once."""
        session_id, credential = _session_credential(session, self.admin_key)
        if seq < 1:
            raise ValueError("seq must be >= 1")
        items: list[Measurement]
        if all(isinstance(item, _MEASUREMENT_MODELS) for item in measurements):
            # every item is a measurement model (the test above, which does not narrow the list's type)
            items = cast("list[Measurement]", list(measurements))
        else:
            items = MEASUREMENTS.validate_python(list(measurements))
        body = b"".join(
            (
                b'{"seq":',
                str(int(seq)).encode(),
                b',"measurements":',
                MEASUREMENTS.dump_json(items),
                b',"include_state":',
                b"true" if include_state else b"false",
                b"}",
            )
        )
        return Call("POST", f"/v1/sessions/{_segment(session_id)}/batches", body, credential)

    def batch_socket(self, session: Session | str) -> Call:
        """The handshake of the session's batch WebSocket (its path and bearer)."""
        session_id, credential = _session_credential(session, self.admin_key)
        return Call("GET", f"/v1/sessions/{_segment(session_id)}/ws", credential=credential)


def next_seq(session: Session | str, seq: int | None) -> int:
    if seq is not None:
        return seq
    if not isinstance(session, Session):
        raise TypeError("give seq explicitly when sending to a session id instead of a Session handle")
    return session.last_seq + 1


def batch_fixes(session: Session | str, seq: int, response: httpx.Response) -> list[Fix]:
    """Parse a batch answer and advance the handle's seq."""
    return result_fixes(session, seq, BatchResult.model_validate_json(response.content))


def result_fixes(session: Session | str, seq: int, result: BatchResult) -> list[Fix]:
    """The fixes of the answer to batch ``seq`` (over HTTP or the WebSocket); advances the handle's seq."""
    if result.seq != seq:
        raise EdgeposError("protocol_error", f"sent seq {seq} but the server answered seq {result.seq}")
    if isinstance(session, Session):
        session.last_seq = max(session.last_seq, seq)
    return result.fixes


def parse_upserted(response: httpx.Response) -> int:
    return int(response.json()["upserted"])


def parse_rsus(response: httpx.Response) -> list[Rsu]:
    return [Rsu.model_validate(item) for item in response.json()["rsus"]]


def parse_rsu(response: httpx.Response) -> Rsu:
    return Rsu.model_validate_json(response.content)


def parse_ephemerides(response: httpx.Response) -> EphemeridesSummary:
    return EphemeridesSummary.model_validate_json(response.content)


def parse_pipelines(response: httpx.Response) -> list[PipelineInfo]:
    return [PipelineInfo.model_validate(item) for item in response.json()["pipelines"]]


def parse_session(response: httpx.Response) -> Session:
    return Session.from_created(SessionCreated.model_validate_json(response.content))


def parse_session_info(response: httpx.Response) -> SessionInfo:
    return SessionInfo.model_validate_json(response.content)


def parse_track(response: httpx.Response) -> Track:
    return Track.model_validate_json(response.content)


def parse_vehicle_key(response: httpx.Response) -> VehicleKey:
    return VehicleKey.model_validate_json(response.content)


def parse_vehicle_import(response: httpx.Response) -> VehicleImport:
    return VehicleImport.model_validate_json(response.content)


def parse_vehicle_page(response: httpx.Response) -> VehiclePage:
    return VehiclePage.model_validate_json(response.content)


def parse_vehicle(response: httpx.Response) -> Vehicle:
    return Vehicle.model_validate_json(response.content)


def parse_revocation(response: httpx.Response) -> Revocation:
    return Revocation.model_validate_json(response.content)


def parse_session_page(response: httpx.Response) -> SessionPage:
    return SessionPage.model_validate_json(response.content)


# -- the fix stream (server-sent events) -----------------------------------------------------------------
STREAM_PATH = "/v1/stream/fixes"


@dataclass(frozen=True)
class StreamRequest:
    """What ``stream_fixes`` asks for; ``headers(last_event_id)`` gives each (re)connection's headers."""

    path: str
    credential: str | None

    def headers(self, last_event_id: str | None) -> dict[str, str]:
        headers = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
        if self.credential:
            headers["Authorization"] = f"Bearer {self.credential}"
        if last_event_id is not None:
            headers["Last-Event-ID"] = last_event_id
        return headers


def stream_request(
    calls: Calls,
    session: Session | None,
    session_id: str | None,
    pipelines: Iterable[str] | None,
    vehicle_ids: Iterable[str] | None,
    max_rate_hz: float | None,
) -> StreamRequest:
    """The stream's path and bearer: a session handle streams its own session with its token, else the
    admin key streams every session's fixes (or ``session_id``'s)."""
    params: list[tuple[str, str]] = []
    if session_id is not None:
        params.append(("session_id", session_id))
    params += [("pipeline", name) for name in pipelines or ()]
    params += [("vehicle_id", vehicle) for vehicle in vehicle_ids or ()]
    if max_rate_hz is not None:
        if not (math.isfinite(max_rate_hz) and max_rate_hz > 0):
            raise ValueError("max_rate_hz must be a positive number")
        params.append(("max_rate_hz", repr(float(max_rate_hz))))
    path = f"{STREAM_PATH}?{urlencode(params, quote_via=quote)}" if params else STREAM_PATH
    return StreamRequest(path, session.token if session is not None else calls.admin_key)


class SseParser:
    """Server-sent events from the lines of a response: feed lines, get (event, data, id) at each blank line."""

    def __init__(self) -> None:
        self._event = ""
        self._data: list[str] = []
        self._id: str | None = None

    def feed(self, line: str) -> tuple[str, str, str | None] | None:
        if line == "":
            if not self._data and not self._event:
                return None
            done = (self._event or "message", "\n".join(self._data), self._id)
            self._event, self._data, self._id = "", [], None
            return done
        if line.startswith(":"):
            return None  # a comment: the server's keep-alive ping
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "event":
            self._event = value
        elif name == "data":
            self._data.append(value)
        elif name == "id":
            self._id = value
        return None


def stream_item(event: str, data: str, event_id: str | None) -> FixEvent | StreamNotice | None:
    """A parsed event as the client's model (None for kinds this client does not know)."""
    if event == "fix" and event_id is not None:
        return FixEvent.model_validate({**json.loads(data), "id": event_id})
    if event in ("missed", "end"):
        return StreamNotice.model_validate({**json.loads(data), "event": event})
    return None
