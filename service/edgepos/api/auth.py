"""Bearer authentication: who is calling, and what their credential opens.

Three kinds of credential reach the service:

- the **admin key** (EDGEPOS_ADMIN_KEY) opens everything, including sessions for any vehicle;
- a **vehicle credential** opens a session for its own vehicle only (POST /v1/sessions): the vehicle's
  key from the registry (EDGEPOS_VEHICLE_AUTH=key, the default) or a token signed by the fleet
  operator (``jwt``); with ``open`` no credential is needed (a lab or a loopback bench);
- a **session token** ``<session_id>.<random>`` opens only its own session;
- the **read key** (EDGEPOS_READ_KEY, optional) opens only the read-only location routes: the MEC 013
  adapter under /location/v3 and every session's fix stream.

The store keeps only SHA-256 digests of keys and tokens, and every comparison of secrets uses
``hmac.compare_digest`` on fixed-length digests (the keys are 256-bit random values, so a fast hash
is enough: there is nothing to guess). 401 means the credential is missing or not valid, with one
message whatever the cause; 403 means it is valid but does not open this resource.

Abuse limits: every failed authentication is counted against the client's address and against the
credential presented (EDGEPOS_AUTH_FAILURE_RATE_PER_S, bursts of EDGEPOS_AUTH_FAILURE_BURST); past
either, the failure is answered 429 with Retry-After instead of 401, and a credential past its own
budget is refused before it is even looked up. A valid credential from an address past its budget
still works: the keys are 256-bit random values that no rate of guessing can find, and a fleet behind
one NAT address must not be locked out by a stranger's failures. Failures are counted in the metrics
and logged with the address and the reason, never the credential. Every request made with a session token counts
against that session's request-rate budget (EDGEPOS_RATE_LIMIT_PER_S). All budgets live in the store,
so they hold across workers and replicas. Authentication is off only with EDGEPOS_AUTH=off, which the
settings refuse unless the instance is declared a lab: then every request is the admin.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import math
import secrets
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.security.utils import get_authorization_scheme_param
from starlette.requests import HTTPConnection

from edgepos.api.context import AppContext, Context
from edgepos.api.errors import ApiError
from edgepos.api.vehicle_jwt import InvalidVehicleToken
from edgepos.store.base import SessionRecord
from edgepos.store.ratelimit import RateLimit

logger = logging.getLogger("edgepos.api")

bearer_scheme = HTTPBearer(
    auto_error=False,
    scheme_name="bearer",
    description="The admin key (EDGEPOS_ADMIN_KEY), a vehicle credential (the vehicle's key from "
    "POST /v1/vehicles, or a fleet-signed token with EDGEPOS_VEHICLE_AUTH=jwt: opens sessions for that "
    "vehicle only), a session token returned by POST /v1/sessions (that session only), or the read "
    "key (EDGEPOS_READ_KEY: the /location/v3 adapter and the fix stream only).",
)
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)]

VEHICLE_KEY_PREFIX = "evk_"
"""Vehicle keys start with this, so a leaked one is recognisable (secret scanners, logs)."""


@dataclass(frozen=True)
class Principal:
    """Who is calling: the admin, the holder of one session's token, or a vehicle.

    ``vehicle_id`` is set for a vehicle credential: it may open sessions for that vehicle only.
    ``vehicle_key_hash`` is set when that credential is a registry key, so that the store can check,
    in the same atomic step that creates the session, that the key is still the vehicle's.
    ``anonymous`` is a caller without credential where EDGEPOS_VEHICLE_AUTH=open allows one."""

    admin: bool
    session_id: str | None = None
    vehicle_id: str | None = None
    vehicle_key_hash: str | None = None
    anonymous: bool = False
    reader: bool = False
    """The read key (EDGEPOS_READ_KEY): the read-only location routes and every session's fix stream."""


def new_session_token(session_id: str) -> str:
    return f"{session_id}.{secrets.token_urlsafe(32)}"


def new_vehicle_key() -> str:
    """A fresh vehicle key: 256 random bits, shown to the operator once."""
    return VEHICLE_KEY_PREFIX + secrets.token_urlsafe(32)


def hash_token(token: str) -> str:
    """What the store keeps instead of a session token or a vehicle key (SHA-256 hex)."""
    return hashlib.sha256(token.encode()).hexdigest()


def _token_session_id(token: str) -> str | None:
    session_id, dot, secret = token.partition(".")
    return session_id if dot and session_id and secret else None


def _is_admin(context: AppContext, secret: str) -> bool:
    return hmac.compare_digest(hashlib.sha256(secret.encode()).digest(), context.admin_key_hash)


def _is_reader(context: AppContext, secret: str) -> bool:
    """The read key (EDGEPOS_READ_KEY), when one is set."""
    expected = context.read_key_hash
    return expected is not None and hmac.compare_digest(hashlib.sha256(secret.encode()).digest(), expected)


_READER_ONLY = ApiError(
    "forbidden",
    "the read key (EDGEPOS_READ_KEY) opens only the location adapter (/location/v3) and the fix stream",
)


def _token_matches(secret: str, token_hash: str) -> bool:
    return hmac.compare_digest(hash_token(secret).encode(), token_hash.encode())


async def _valid_session_token(context: AppContext, secret: str) -> bool:
    session_id = _token_session_id(secret)
    if session_id is None:
        return False
    record = await context.store.get(session_id)
    return record is not None and _token_matches(secret, record.token_hash)


_LAB = Principal(admin=True)
INVALID_CREDENTIAL = "the bearer credential is not valid (unknown, revoked or expired key or token)"
_INVALID = INVALID_CREDENTIAL


def _auth_off(context: AppContext) -> bool:
    """True on a lab instance started with EDGEPOS_AUTH=off: every caller is the admin."""
    return not context.settings.auth_enabled


def client_address(connection: HTTPConnection) -> str:
    """The caller's address as the server sees it (behind a reverse proxy, uvicorn's
    --forwarded-allow-ips decides whether X-Forwarded-For is believed)."""
    return connection.client.host if connection.client is not None else "unknown"


def _retry_after(wait_s: float) -> str:
    return str(max(1, math.ceil(wait_s)))


def _limited(message: str, wait_s: float) -> ApiError:
    retry_after = _retry_after(wait_s)
    return ApiError(
        "rate_limited", f"{message}; retry after {retry_after} s", headers={"Retry-After": retry_after}
    )


async def _refuse(
    context: AppContext, request: HTTPConnection, secret: str | None, reason: str, error: ApiError
) -> ApiError:
    """Count a failed authentication (address and credential budgets, metrics, a log line without
    the credential) and return the error to raise: ``error``, or 429 once a budget is spent."""
    context.metrics.auth_failures.labels(reason).inc()
    address = client_address(request)
    logger.warning(
        "authentication failed",
        extra={"event": "auth_failed", "reason": reason, "client": address, "path": request.url.path},
    )
    limit = context.settings.auth_failure_limit
    waits = [await context.store.take_request(f"authfail:addr:{address}", limit)]
    if secret:
        waits.append(await context.store.take_request(_credential_key(secret), limit))
    wait_s = max(waits)
    if wait_s > 0:
        context.metrics.rate_limited.labels("auth_failures").inc()
        return _limited(
            "too many failed authentications from this address or with this credential "
            f"({limit.rate_per_s:g}/s, bursts of {limit.burst}; EDGEPOS_AUTH_FAILURE_RATE_PER_S)",
            wait_s,
        )
    return error


def _credential_key(secret: str) -> str:
    """The failure budget of one presented credential (by digest: the store never sees a secret)."""
    return f"authfail:cred:{hash_token(secret)}"


def _unauthorized(message: str = _INVALID) -> ApiError:
    return ApiError("unauthorized", message)


_MISSING = "missing credentials: send 'Authorization: Bearer <key or token>'"


async def charge_rate_limit(context: AppContext, session_id: str) -> None:
    """Count one request of this session's token; 429 rate_limited with Retry-After when over."""
    limit = context.settings.rate_limit
    if limit is None:
        return
    wait_s = await context.store.take_request(f"session:{session_id}", limit)
    if wait_s > 0:
        context.metrics.rate_limited.labels("session_requests").inc()
        raise _limited(
            f"this session's token is over its request rate ({limit.rate_per_s:g}/s, bursts of "
            f"{limit.burst}; EDGEPOS_RATE_LIMIT_PER_S)",
            wait_s,
        )


async def _vehicle(context: AppContext, secret: str) -> Principal | None:
    """The vehicle a vehicle credential stands for, None when it is not one (or not valid)."""
    mode = context.settings.vehicle_auth
    if mode == "key":
        if not secret.startswith(VEHICLE_KEY_PREFIX):
            return None
        key_hash = hash_token(secret)
        vehicle_id = await context.store.vehicle_of_key(key_hash)
        return (
            None if vehicle_id is None else Principal(False, vehicle_id=vehicle_id, vehicle_key_hash=key_hash)
        )
    if mode == "jwt" and context.vehicle_keys is not None and secret.count(".") == 2:
        try:
            vehicle_id = context.vehicle_keys.verify(secret, context.settings.vehicle_jwt_audience)
        except InvalidVehicleToken as error:
            logger.debug(
                "vehicle token refused", extra={"event": "vehicle_token_refused", "cause": error.cause}
            )
            return None
        return Principal(False, vehicle_id=vehicle_id)
    return None


async def require_admin(request: Request, context: Context, credentials: Credentials) -> Principal:
    """Only the admin key passes; a valid session token or vehicle credential gets 403."""
    if _auth_off(context):
        return _LAB
    secret = None if credentials is None else credentials.credentials
    if not secret:
        raise await _refuse(context, request, None, "missing", _unauthorized(_MISSING))
    if _is_admin(context, secret):
        return Principal(admin=True)
    if _is_reader(context, secret):
        raise await _refuse(context, request, None, "forbidden", _READER_ONLY)
    if await _valid_session_token(context, secret) or await _vehicle(context, secret) is not None:
        raise await _refuse(
            context,
            request,
            secret,
            "forbidden",
            ApiError(
                "forbidden",
                "this call needs the admin key; a session token or vehicle credential does not open it",
            ),
        )
    raise await _refuse(context, request, secret, "invalid", _unauthorized())


async def require_reader(request: Request, context: Context, credentials: Credentials) -> Principal:
    """The admin key or the read key (EDGEPOS_READ_KEY) passes: the read-only location routes (the MEC 013
    adapter). A valid session token or vehicle credential gets 403."""
    if _auth_off(context):
        return _LAB
    secret = None if credentials is None else credentials.credentials
    if not secret:
        raise await _refuse(context, request, None, "missing", _unauthorized(_MISSING))
    if _is_admin(context, secret):
        return Principal(admin=True)
    if _is_reader(context, secret):
        return Principal(admin=False, reader=True)
    if await _valid_session_token(context, secret) or await _vehicle(context, secret) is not None:
        raise await _refuse(
            context,
            request,
            secret,
            "forbidden",
            ApiError("forbidden", "this call needs the admin key or the read key (EDGEPOS_READ_KEY)"),
        )
    raise await _refuse(context, request, secret, "invalid", _unauthorized())


async def require_stream_reader(request: Request, context: Context, credentials: Credentials) -> Principal:
    """The read key, or whatever :func:`require_any` lets in (a session token streams its own fixes)."""
    secret = None if credentials is None else credentials.credentials
    if secret and not _auth_off(context) and _is_reader(context, secret):
        return Principal(admin=False, reader=True)
    return await require_any(request, context, credentials)


async def require_any(request: Request, context: Context, credentials: Credentials) -> Principal:
    """The admin key, any live session's token, or a vehicle credential passes (the site's shared,
    read-only information: a vehicle may read the RSU map before it opens its session)."""
    if _auth_off(context):
        return _LAB
    secret = None if credentials is None else credentials.credentials
    if not secret:
        raise await _refuse(context, request, None, "missing", _unauthorized(_MISSING))
    if _is_admin(context, secret):
        return Principal(admin=True)
    session_id = _token_session_id(secret)
    if session_id is not None and await _valid_session_token(context, secret):
        await charge_rate_limit(context, session_id)
        return Principal(admin=False, session_id=session_id)
    vehicle = await _vehicle(context, secret)
    if vehicle is not None:
        return vehicle
    if _is_reader(context, secret):
        raise await _refuse(context, request, None, "forbidden", _READER_ONLY)
    raise await _refuse(context, request, secret, "invalid", _unauthorized())


async def require_vehicle(request: Request, context: Context, credentials: Credentials) -> Principal:
    """Who may open a session: the admin key (any vehicle) or a vehicle credential (its own vehicle;
    the route checks the body's vehicle_id against it), or nobody in particular with
    EDGEPOS_VEHICLE_AUTH=open. A client address past its failure budget is refused first."""
    if _auth_off(context):
        return _LAB
    secret = None if credentials is None else credentials.credentials
    if secret and _is_admin(context, secret):
        return Principal(admin=True)
    if context.settings.vehicle_auth == "open":
        return Principal(admin=False, anonymous=True)
    if not secret:
        raise await _refuse(context, request, None, "missing", _unauthorized(_MISSING))
    wait_s = await context.store.request_wait(_credential_key(secret), context.settings.auth_failure_limit)
    if wait_s > 0:  # a credential that keeps failing (a revoked key in a loop) is not even looked up
        context.metrics.rate_limited.labels("auth_failures").inc()
        raise _limited("this credential failed too often (EDGEPOS_AUTH_FAILURE_RATE_PER_S)", wait_s)
    vehicle = await _vehicle(context, secret)
    if vehicle is None:
        raise await _refuse(context, request, secret, "invalid", _unauthorized())
    return vehicle


async def authorise_session_creation(
    request: Request, context: AppContext, principal: Principal, vehicle_id: str
) -> None:
    """403 when a vehicle credential names another vehicle; 429 when the credential or the address
    opens sessions faster than its budget. The admin key is not limited."""
    if principal.admin:
        return
    if principal.vehicle_id is not None and principal.vehicle_id != vehicle_id:
        raise await _refuse(
            context,
            request,
            None,
            "wrong_vehicle",
            ApiError(
                "forbidden",
                f"this vehicle credential opens sessions for its own vehicle only, not for {vehicle_id!r}",
            ),
        )
    settings = context.settings
    budgets: list[tuple[str, RateLimit, str]] = [
        (f"create:addr:{client_address(request)}", settings.session_create_address_limit, "this address"),
    ]
    if principal.vehicle_id is not None:
        budgets.append((f"create:vehicle:{vehicle_id}", settings.session_create_limit, "this vehicle"))
    for key, limit, whose in budgets:
        wait_s = await context.store.take_request(key, limit)
        if wait_s > 0:
            context.metrics.rate_limited.labels("session_creations").inc()
            raise _limited(
                f"{whose} opens sessions faster than allowed ({limit.rate_per_s:g}/s, bursts of {limit.burst}; "
                "EDGEPOS_SESSION_CREATE_RATE_PER_S and EDGEPOS_SESSION_CREATE_ADDRESS_RATE_PER_S)",
                wait_s,
            )


async def require_session(
    request: Request,
    session_id: Annotated[str, Path(description="Session identifier returned by POST /v1/sessions.")],
    context: Context,
    credentials: Credentials,
) -> Principal:
    """The admin key, or this session's own token (another session's valid token gets 403).

    A token of a session that a newer session of its vehicle replaced gets 409 naming the newer one."""
    secret = None if credentials is None else credentials.credentials
    principal, _record = await authenticate_session(context, request, session_id, secret)
    return principal


async def require_batch_session(
    request: Request,
    session_id: Annotated[str, Path(description="Session identifier returned by POST /v1/sessions.")],
    context: Context,
    credentials: Credentials,
) -> Principal:
    """:func:`require_session` for the batch route: the record the check read is kept for the batch to
    apply on, and it may be the one this worker wrote last (see ``SessionStore.get_for_batch``)."""
    secret = None if credentials is None else credentials.credentials
    principal, record = await authenticate_session(context, request, session_id, secret, for_batch=True)
    if record is not None:
        request.state.session_record = (
            record  # the batch route applies on it (see session_service.apply_batch)
        )
    return principal


def bearer_secret(connection: HTTPConnection) -> str | None:
    """The credential of an ``Authorization: Bearer ...`` header (what HTTPBearer reads for a route), for a
    WebSocket handshake, which FastAPI's security dependencies do not see."""
    scheme, secret = get_authorization_scheme_param(connection.headers.get("authorization"))
    return secret or None if scheme.lower() == "bearer" else None


async def authenticate_session(
    context: AppContext,
    connection: HTTPConnection,
    session_id: str,
    secret: str | None,
    *,
    for_batch: bool = False,
) -> tuple[Principal, SessionRecord | None]:
    """The check of :func:`require_session`, shared by the HTTP routes and the WebSocket handshake: the
    principal, and the session's record when a session token was checked against it (None for the
    admin). Charges the session's request-rate budget once for a session token. ``for_batch``: the
    record may be the one this worker wrote last, not read now (``SessionStore.get_for_batch``); a batch
    applies only on the version it names, and a session gone meanwhile is refused as here
    (``session_service.apply_batch``)."""
    if _auth_off(context):
        return _LAB, None
    if not secret:
        raise await _refuse(context, connection, None, "missing", _unauthorized(_MISSING))
    if _is_admin(context, secret):
        return Principal(admin=True), None
    token_session = _token_session_id(secret)
    if token_session is None:
        if _is_reader(context, secret):
            raise await _refuse(context, connection, None, "forbidden", _READER_ONLY)
        raise await _refuse(context, connection, secret, "invalid", _unauthorized())
    if token_session != session_id:
        if await _valid_session_token(context, secret):
            raise ApiError("forbidden", "a session token opens only its own session")
        raise await _refuse(context, connection, secret, "invalid", _unauthorized())
    # the stored answer is left out: the batch routes apply the next seq on this record, and read afresh
    # (answer included) for anything else, a replay among them
    if for_batch:
        record = await context.store.get_for_batch(session_id)
    else:
        record = await context.store.get(session_id, with_response=False)
    if record is None:
        superseded = await context.store.supersession(session_id)
        if superseded is not None and _token_matches(secret, superseded.token_hash):
            raise superseded_error(session_id, superseded.superseded_by)
        # A token of a session that does not exist (never did, expired, deleted, revoked) is answered
        # exactly as a wrong token of one that does: a stranger learns nothing by probing ids.
        raise await _refuse(context, connection, secret, "invalid", _unauthorized())
    if not _token_matches(secret, record.token_hash):
        raise await _refuse(context, connection, secret, "invalid", _unauthorized())
    await charge_rate_limit(context, session_id)
    return Principal(admin=False, session_id=session_id), record


def superseded_error(session_id: str, newer: str) -> ApiError:
    """409 superseded: the vehicle opened a newer session, which is now its only live one."""
    return ApiError(
        "superseded",
        f"session {session_id!r} was superseded by session {newer!r}, opened later for the same vehicle "
        "(a vehicle has one live session); this session's token opens nothing any more, use the newer session",
    )
