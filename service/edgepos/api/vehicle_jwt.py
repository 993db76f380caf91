"""Vehicle tokens signed by the fleet operator: load the operator's JWKS, verify a token, get the vehicle id.

Why: a fleet operator already signs its vehicles' identity, so the service can accept the operator's
JWTs instead of handing out its own credentials. The operator publishes its public keys as a JWKS file
(setting ``EDGEPOS_VEHICLE_JWKS``); a vehicle sends a compact JWS whose ``sub`` is its vehicle id and
whose ``aud`` names this service (``edgepos`` unless configured otherwise).

What is accepted, and nothing else:

* ``alg`` ES256 (EC P-256 key) or RS256 (RSA key of at least 2048 bits). The verifying algorithm is
  bound to the key, never taken from the token, so ``none``, HS256 signed with the public key as HMAC
  secret (key confusion) and the like are refused.
* The key is found by the token's ``kid``; a token without ``kid`` only when the set holds exactly
  one key usable for the token's ``alg``. A ``kid`` that names no key is refused.
* ``exp`` and ``sub`` are required, ``aud`` must contain the expected audience, ``nbf`` and ``iat``
  are checked when present; times allow :data:`CLOCK_SKEW_S` of clock skew. ``sub`` is a non-empty
  printable string of at most :data:`MAX_SUB_LENGTH` characters.

Every refusal raises :class:`InvalidVehicleToken` with the same message, so a caller that answers
401 with ``str(error)`` tells an attacker nothing about which check failed; the cause is in
``error.cause`` for a debug log field and never contains the token. A JWKS file the service cannot use
entirely (unreadable, not JSON, private or unsupported keys, RSA keys under 2048 bits, no usable key)
raises :class:`JwksError` naming the file, so the service refuses to start rather than running with
part of the operator's keys.

All JWS/JWT parsing and cryptography is PyJWT's (``jwt.get_unverified_header``, ``jwt.PyJWK``,
``jwt.decode``). Only the time claims are checked here, because ``jwt.decode`` reads the clock itself
and :meth:`VehicleKeySet.verify` takes ``now`` so that tests and replays do not depend on timing.
This module imports nothing from FastAPI.
"""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import jwt
from cryptography.hazmat.primitives.asymmetric import ec, rsa
from jwt.utils import base64url_decode, base64url_encode

DEFAULT_AUDIENCE: Final = "edgepos"
"""The ``aud`` a vehicle token must carry unless the service is configured with another audience."""

CLOCK_SKEW_S: Final = 30.0
"""Seconds of clock skew tolerated between the operator, the vehicle and this service: a token counts
as expired only ``CLOCK_SKEW_S`` after its ``exp``, and ``nbf``/``iat`` may lie up to that far ahead."""

MAX_SUB_LENGTH: Final = 128
"""Longest vehicle id (``sub``) accepted, in characters."""

MIN_RSA_BITS: Final = 2048
"""Smallest RSA modulus accepted in the JWKS; a smaller key is refused when the file is loaded."""

MAX_TOKEN_LENGTH: Final = 8192
"""Longest token looked at; longer strings are refused before any decoding work."""

MAX_JWKS_BYTES: Final = 1 << 20
"""Largest JWKS file read."""

INVALID_TOKEN_MESSAGE: Final = "invalid vehicle token"
"""The one message of every :class:`InvalidVehicleToken`, whatever the cause."""

# The algorithm each supported key type verifies with: the only two accepted.
_ALG_BY_KTY: Final[Mapping[str, str]] = {"EC": "ES256", "RSA": "RS256"}
ALGORITHMS: Final = tuple(_ALG_BY_KTY.values())
"""The token algorithms accepted."""

# JWK members that only a private key has (RFC 7518 §6.2.2, §6.3.2) or a symmetric one (``k``).
_PRIVATE_MEMBERS: Final = frozenset({"d", "p", "q", "dp", "dq", "qi", "oth", "k"})

# Compact JWS: three base64url segments without padding (RFC 7515 §2, §7.1).
_COMPACT_JWS: Final = re.compile(r"[A-Za-z0-9_-]*\.[A-Za-z0-9_-]*\.[A-Za-z0-9_-]*")

# PyJWT's own failures, and what they mean for the log's cause field (first match wins).
_DECODE_CAUSES: Final[tuple[tuple[type[Exception], str], ...]] = (
    (jwt.InvalidSignatureError, "bad signature"),
    (jwt.InvalidAlgorithmError, "algorithm not allowed for the key"),
    (jwt.InvalidAudienceError, "wrong audience"),
    (jwt.InvalidKeyError, "key refused"),
    (jwt.DecodeError, "malformed token"),
)


class InvalidVehicleToken(Exception):
    """A vehicle token was refused. ``str()`` is always :data:`INVALID_TOKEN_MESSAGE`;
    ``cause`` says why, for a debug log field, and never contains the token."""

    def __init__(self, cause: str) -> None:
        super().__init__(INVALID_TOKEN_MESSAGE)
        self.cause = cause


class JwksError(Exception):
    """The JWKS file cannot be used; the message names the file and says why."""


@dataclass(frozen=True)
class VehicleKey:
    """One usable public key of the operator's JWKS."""

    kid: str | None
    alg: str
    jwk: jwt.PyJWK


def _shown(value: Any) -> str:
    """A header value for a log cause: repr (so control characters are escaped), cut short."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _number(value: Any) -> float | None:
    """A NumericDate claim as a float, or None when it is not a finite JSON number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _canonical(token: str) -> bool:
    """Whether every segment is the one base64url spelling of its bytes (no stray trailing bits), so
    an accepted token cannot be re-spelled into a different string that is accepted too."""
    try:
        return all(base64url_encode(base64url_decode(part)).decode() == part for part in token.split("."))
    except (ValueError, TypeError):
        return False


class VehicleKeySet:
    """The operator's usable public keys, and verification of vehicle tokens against them."""

    def __init__(self, keys: Sequence[VehicleKey], source: str = "JWKS", ignored: Sequence[str] = ()) -> None:
        """``keys`` must be non-empty with distinct kids; ``ignored`` describes keys left out (for logs)."""
        if not keys:
            raise JwksError(f"{source}: no usable signing key (ES256 on P-256 or RS256)")
        kids = [key.kid for key in keys if key.kid is not None]
        if len(kids) != len(set(kids)):
            raise JwksError(f"{source}: two usable keys share a kid")
        self.keys: tuple[VehicleKey, ...] = tuple(keys)
        self.source = source
        self.ignored: tuple[str, ...] = tuple(ignored)

    def __len__(self) -> int:
        return len(self.keys)

    def _select(self, header: Mapping[str, Any]) -> VehicleKey:
        """The key that must have signed a token with this (unverified) header."""
        alg = header.get("alg")
        if not isinstance(alg, str) or alg not in ALGORITHMS:
            raise InvalidVehicleToken(f"alg {_shown(alg)} not allowed")
        if "kid" in header:
            kid = header["kid"]
            key = next((key for key in self.keys if key.kid is not None and key.kid == kid), None)
            if key is None:
                raise InvalidVehicleToken(f"unknown kid {_shown(kid)}")
            if key.alg != alg:
                raise InvalidVehicleToken(f"alg {alg} does not match key {_shown(kid)} ({key.alg})")
            return key
        candidates = [key for key in self.keys if key.alg == alg]
        if len(candidates) != 1:
            raise InvalidVehicleToken(f"no kid and {len(candidates)} keys for {alg}")
        return candidates[0]

    def verify(self, token: str, audience: str, now: float | None = None) -> str:
        """The vehicle id (``sub``) of a valid token for ``audience`` at time ``now`` (Unix seconds,
        default the clock); any other token raises :class:`InvalidVehicleToken`."""
        if not isinstance(audience, str) or not audience:
            raise ValueError("audience must be a non-empty string")
        if now is not None and not math.isfinite(now):
            raise ValueError("now must be a finite time")
        if not isinstance(token, str) or not token:
            raise InvalidVehicleToken("no token")
        if len(token) > MAX_TOKEN_LENGTH:
            raise InvalidVehicleToken("token too long")
        if not _COMPACT_JWS.fullmatch(token) or not _canonical(token):
            raise InvalidVehicleToken("not a compact JWS")
        try:
            header = jwt.get_unverified_header(token)
            key = self._select(header)
            claims = jwt.decode(
                token,
                key.jwk.key,
                algorithms=[key.alg],  # from the key, never from the token
                audience=audience,
                options={
                    "require": ["exp", "sub"],
                    # checked below against ``now``: jwt.decode would read the clock itself
                    "verify_exp": False,
                    "verify_nbf": False,
                    "verify_iat": False,
                    "enforce_minimum_key_length": True,
                },
            )
        except jwt.MissingRequiredClaimError as error:
            raise InvalidVehicleToken(f"missing claim {error.claim}") from None
        except jwt.PyJWTError as error:
            cause = next((text for kind, text in _DECODE_CAUSES if isinstance(error, kind)), None)
            raise InvalidVehicleToken(cause or f"refused by PyJWT ({type(error).__name__})") from None
        except (ValueError, TypeError, OverflowError, RecursionError, UnicodeError) as error:
            raise InvalidVehicleToken(f"malformed token ({type(error).__name__})") from None
        return _check_claims(claims, time.time() if now is None else now)


def _check_claims(claims: Mapping[str, Any], now: float) -> str:
    """The time claims against ``now`` with :data:`CLOCK_SKEW_S`, then ``sub``; returns ``sub``."""
    exp = _number(claims.get("exp"))
    if exp is None:
        raise InvalidVehicleToken("exp is not a number")
    if exp <= now - CLOCK_SKEW_S:
        raise InvalidVehicleToken("expired")
    for name in ("nbf", "iat"):
        if name in claims:
            value = _number(claims[name])
            if value is None:
                raise InvalidVehicleToken(f"{name} is not a number")
            if value > now + CLOCK_SKEW_S:
                raise InvalidVehicleToken(f"not yet valid ({name} in the future)")
    sub = claims.get("sub")
    if not isinstance(sub, str) or not sub:
        raise InvalidVehicleToken("sub is not a non-empty string")
    if len(sub) > MAX_SUB_LENGTH:
        raise InvalidVehicleToken(f"sub longer than {MAX_SUB_LENGTH} characters")
    if not sub.isprintable():
        raise InvalidVehicleToken("sub has unprintable characters")
    return sub


def _load_key(index: int, member: Any, where: str) -> VehicleKey | str:
    """One JWKS member as a usable key, or a description of why it is not usable (for logs).
    A member the service must not accept at all raises :class:`JwksError`."""
    label = f"{where}: key {index}"
    if not isinstance(member, dict):
        raise JwksError(f"{label} is not a JSON object")
    kty = member.get("kty")
    if not isinstance(kty, str) or kty not in _ALG_BY_KTY:
        raise JwksError(f"{label}: unsupported key type {_shown(kty)} (only EC P-256 and RSA are accepted)")
    private = sorted(_PRIVATE_MEMBERS & member.keys())
    if private:
        raise JwksError(
            f"{label} is a private key (has {', '.join(private)}): the vehicle JWKS must hold the "
            "operator's public keys only; remove the private parts and keep them secret"
        )
    if kty == "EC" and member.get("crv") != "P-256":
        raise JwksError(f"{label}: unsupported curve {_shown(member.get('crv'))} (only P-256 for ES256)")
    alg = _ALG_BY_KTY[kty]
    kid = member.get("kid")
    if kid is not None and (not isinstance(kid, str) or not kid):
        raise JwksError(f"{label}: kid must be a non-empty string")
    label = f"{label} (kid {kid!r})" if kid is not None else label
    try:
        jwk = jwt.PyJWK(member, algorithm=alg)  # the algorithm follows the key type, not its "alg"
    except Exception as error:  # noqa: BLE001 - whatever PyJWT or cryptography cannot load
        raise JwksError(f"{label}: PyJWT cannot load it ({type(error).__name__}: {error})") from None
    if kty == "EC":
        if not isinstance(jwk.key, ec.EllipticCurvePublicKey) or not isinstance(jwk.key.curve, ec.SECP256R1):
            raise JwksError(f"{label}: not an EC P-256 public key")
    elif not isinstance(jwk.key, rsa.RSAPublicKey):
        raise JwksError(f"{label}: not an RSA public key")
    elif jwk.key.key_size < MIN_RSA_BITS:
        raise JwksError(f"{label}: RSA key of {jwk.key.key_size} bits, at least {MIN_RSA_BITS} required")
    use = member.get("use")
    if use is not None and use != "sig":
        return f"{label}: use {_shown(use)} is not 'sig'"
    if "alg" in member and member["alg"] != alg:
        return f"{label}: alg {_shown(member['alg'])} is not {alg}"
    key_ops = member.get("key_ops")
    if key_ops is not None and (not isinstance(key_ops, list) or "verify" not in key_ops):
        return f"{label}: key_ops {_shown(key_ops)} does not allow 'verify'"
    return VehicleKey(kid=kid, alg=alg, jwk=jwk)


def load_vehicle_jwks(path: Path) -> VehicleKeySet:
    """The usable keys of the JWKS file at ``path``; any problem with the file raises :class:`JwksError`.

    Keys whose ``use``, ``alg`` or ``key_ops`` say they are not for ES256/RS256 signatures are left out
    (listed in ``ignored``); private keys, unsupported key types or curves, RSA keys under
    :data:`MIN_RSA_BITS` bits and keys PyJWT cannot load make the whole file an error.
    """
    where = f"vehicle JWKS {str(path)!r}"
    try:
        with open(path, "rb") as file:
            data = file.read(MAX_JWKS_BYTES + 1)
    except OSError as error:
        raise JwksError(f"{where}: cannot read it ({error.strerror or type(error).__name__})") from None
    if len(data) > MAX_JWKS_BYTES:
        raise JwksError(f"{where}: larger than {MAX_JWKS_BYTES} bytes")
    try:
        document = json.loads(data)
    except (ValueError, RecursionError) as error:
        raise JwksError(f"{where}: not JSON ({error})") from None
    if not isinstance(document, dict) or "keys" not in document:
        raise JwksError(f'{where}: not a JWKS (a JSON object with a "keys" array)')
    members = document["keys"]
    if not isinstance(members, list):
        raise JwksError(f'{where}: "keys" is not an array')
    keys: list[VehicleKey] = []
    ignored: list[str] = []
    for index, member in enumerate(members):
        loaded = _load_key(index, member, where)
        if isinstance(loaded, VehicleKey):
            keys.append(loaded)
        else:
            ignored.append(loaded)
    return VehicleKeySet(keys, source=where, ignored=ignored)
