"""Bearer authentication: the admin key opens everything, a session token only its own session.

Session tokens look like ``<session_id>.<random>``; the store keeps only their SHA-256, and every
comparison of secrets uses ``hmac.compare_digest`` on fixed-length digests. 401 means the
credential is missing or not valid; 403 means it is valid but does not open this resource.

Every request made with a session token counts against that session's request-rate budget
(EDGEPOS_RATE_LIMIT_PER_S, bursts of EDGEPOS_RATE_LIMIT_BURST), kept in the store so that it holds
across workers and replicas; past it the answer is 429 with Retry-After. The budget is charged only
after the token is verified, so nobody can spend another vehicle's budget. The admin key is not
limited. Without EDGEPOS_ADMIN_KEY a random key is generated. Authentication is off only with
EDGEPOS_AUTH=off, which the settings refuse unless the instance is declared a lab (EDGEPOS_LAB=true,
``edgepos serve --lab``): then every request is the admin.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import secrets
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Path
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from edgepos.api.context import AppContext, Context
from edgepos.api.errors import ApiError

bearer_scheme = HTTPBearer(
    auto_error=False,
    scheme_name="bearer",
    description="The admin key (EDGEPOS_ADMIN_KEY) or a session token returned by POST /v1/sessions.",
)
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)]


@dataclass(frozen=True)
class Principal:
    """Who is calling: the admin, or the holder of one session's token."""

    admin: bool
    session_id: str | None = None


def new_session_id() -> str:
    return secrets.token_hex(16)


def new_session_token(session_id: str) -> str:
    return f"{session_id}.{secrets.token_urlsafe(32)}"


def hash_token(token: str) -> str:
    """What the store keeps instead of a session token."""
    return hashlib.sha256(token.encode()).hexdigest()


def _token_session_id(token: str) -> str | None:
    session_id, dot, secret = token.partition(".")
    return session_id if dot and session_id and secret else None


def _is_admin(context: AppContext, secret: str) -> bool:
    return hmac.compare_digest(hashlib.sha256(secret.encode()).digest(), context.admin_key_hash)


def _token_matches(secret: str, token_hash: str) -> bool:
    return hmac.compare_digest(hash_token(secret).encode(), token_hash.encode())


async def _valid_session_token(context: AppContext, secret: str) -> bool:
    session_id = _token_session_id(secret)
    if session_id is None:
        return False
    record = await context.store.get(session_id)
    return record is not None and _token_matches(secret, record.token_hash)


_LAB = Principal(admin=True)


def _auth_off(context: AppContext) -> bool:
    """True on a lab instance started with EDGEPOS_AUTH=off: every caller is the admin."""
    return not context.settings.auth_enabled


def _secret(credentials: HTTPAuthorizationCredentials | None) -> str:
    if credentials is None or not credentials.credentials:
        raise ApiError("unauthorized", "missing credentials: send 'Authorization: Bearer <key or token>'")
    return credentials.credentials


async def charge_rate_limit(context: AppContext, session_id: str) -> None:
    """Count one request of this session's token; 429 rate_limited with Retry-After when over."""
    limit = context.settings.rate_limit
    if limit is None:
        return
    wait_s = await context.store.take_request(f"session:{session_id}", limit)
    if wait_s > 0:
        retry_after = max(1, math.ceil(wait_s))
        raise ApiError(
            "rate_limited",
            f"this session's token is over its request rate ({limit.rate_per_s:g}/s, bursts of "
            f"{limit.burst}; EDGEPOS_RATE_LIMIT_PER_S); retry after {retry_after} s",
            headers={"Retry-After": str(retry_after)},
        )


_INVALID = "the bearer credential is not valid (unknown key, or the session's token does not match)"


async def require_admin(
    context: Context,
    credentials: Credentials,
) -> Principal:
    """Only the admin key passes; a valid session token gets 403."""
    if _auth_off(context):
        return _LAB
    secret = _secret(credentials)
    if _is_admin(context, secret):
        return Principal(admin=True)
    if await _valid_session_token(context, secret):
        raise ApiError("forbidden", "this call needs the admin key; a session token does not open it")
    raise ApiError("unauthorized", _INVALID)


async def require_any(
    context: Context,
    credentials: Credentials,
) -> Principal:
    """The admin key or any live session's token passes."""
    if _auth_off(context):
        return _LAB
    secret = _secret(credentials)
    if _is_admin(context, secret):
        return Principal(admin=True)
    session_id = _token_session_id(secret)
    if session_id is not None and await _valid_session_token(context, secret):
        await charge_rate_limit(context, session_id)
        return Principal(admin=False, session_id=session_id)
    raise ApiError("unauthorized", _INVALID)


async def require_session(
    session_id: Annotated[str, Path(description="Session identifier returned by POST /v1/sessions.")],
    context: Context,
    credentials: Credentials,
) -> Principal:
    """The admin key, or this session's own token (another session's valid token gets 403)."""
    if _auth_off(context):
        return _LAB
    secret = _secret(credentials)
    if _is_admin(context, secret):
        return Principal(admin=True)
    token_session = _token_session_id(secret)
    if token_session is None:
        raise ApiError("unauthorized", _INVALID)
    if token_session != session_id:
        if await _valid_session_token(context, secret):
            raise ApiError("forbidden", "a session token opens only its own session")
        raise ApiError("unauthorized", _INVALID)
    record = await context.store.get(session_id)
    if record is None:
        raise ApiError("not_found", f"no session {session_id!r} (it may have expired or been deleted)")
    if not _token_matches(secret, record.token_hash):
        raise ApiError("unauthorized", _INVALID)
    await charge_rate_limit(context, session_id)
    return Principal(admin=False, session_id=session_id)
