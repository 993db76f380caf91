"""Vehicle tokens signed by the fleet operator (edgepos.api.vehicle_jwt): ES256 and RS256 from a JWKS file
are accepted, every other token is refused with one exception and one message, and a JWKS the service
must not use is an error naming the file. A hypothesis property forges tokens from valid ones. Times are
always passed as ``now``: nothing here depends on the clock."""

from __future__ import annotations

import hashlib
import hmac
import json
import string
from pathlib import Path
from typing import Any

import jwt
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, rsa
from edgepos.api.vehicle_jwt import (
    CLOCK_SKEW_S,
    DEFAULT_AUDIENCE,
    INVALID_TOKEN_MESSAGE,
    MAX_SUB_LENGTH,
    InvalidVehicleToken,
    JwksError,
    VehicleKeySet,
    load_vehicle_jwks,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from jwt.algorithms import ECAlgorithm, RSAAlgorithm
from jwt.utils import base64url_decode, base64url_encode

NOW = 1_700_000_000
AUD = DEFAULT_AUDIENCE

EC_KEY = ec.generate_private_key(ec.SECP256R1())
RSA_KEY = rsa.generate_private_key(public_exponent=65537, key_size=2048)
EC_KEY_2 = ec.generate_private_key(ec.SECP256R1())  # a second genuine key
EC_ATTACKER = ec.generate_private_key(ec.SECP256R1())
EC384_ATTACKER = ec.generate_private_key(ec.SECP384R1())
RSA_ATTACKER = rsa.generate_private_key(public_exponent=65537, key_size=2048)


def b64(data: bytes) -> str:
    return base64url_encode(data).decode()


def b64json(value: Any, sort_keys: bool = False) -> str:
    return b64(json.dumps(value, separators=(",", ":"), sort_keys=sort_keys).encode())


def public_pem(private: Any) -> bytes:
    return private.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )


def public_jwk(private: Any, kid: str | None = None, **members: Any) -> dict[str, Any]:
    algorithm = ECAlgorithm if isinstance(private, ec.EllipticCurvePrivateKey) else RSAAlgorithm
    jwk = json.loads(algorithm.to_jwk(private.public_key()))
    if kid is not None:
        jwk["kid"] = kid
    return {**jwk, **members}


def private_jwk(private: Any, kid: str) -> dict[str, Any]:
    algorithm = ECAlgorithm if isinstance(private, ec.EllipticCurvePrivateKey) else RSAAlgorithm
    return {**json.loads(algorithm.to_jwk(private)), "kid": kid}


def write_jwks(path: Path, *keys: Any) -> Path:
    path.write_text(json.dumps({"keys": list(keys)}))
    return path


def claims(**changes: Any) -> dict[str, Any]:
    """Valid claims at NOW; a change to None drops the claim."""
    base: dict[str, Any] = {"sub": "veh-42", "aud": AUD, "iat": NOW - 10, "exp": NOW + 300}
    base.update(changes)
    return {name: value for name, value in base.items() if value is not None}


def sign(private: Any, payload: dict[str, Any], alg: str | None = None, kid: str | None = None) -> str:
    if alg is None:
        alg = "ES256" if isinstance(private, ec.EllipticCurvePrivateKey) else "RS256"
    return jwt.encode(payload, private, algorithm=alg, headers={"kid": kid} if kid else None)


def hand_signed(header: dict[str, Any], payload: dict[str, Any], key: bytes, digest: str = "sha256") -> str:
    """A token HMAC-signed with ``key`` (PyJWT refuses a PEM as HMAC secret, an attacker does not)."""
    signing_input = f"{b64json(header, sort_keys=True)}.{b64json(payload)}"
    signature = hmac.new(key, signing_input.encode(), getattr(hashlib, digest)).digest()
    return f"{signing_input}.{b64(signature)}"


def raw_signed(header: dict[str, Any], payload: dict[str, Any], private: Any) -> str:
    """A token with a header jwt.encode refuses to write, signed with ``private`` under the header's alg."""
    signing_input = f"{b64json(header, sort_keys=True)}.{b64json(payload)}"
    signature = jwt.get_algorithm_by_name(header["alg"]).sign(signing_input.encode(), private)
    return f"{signing_input}.{b64(signature)}"


def operator_jwks(path: Path) -> Path:
    return write_jwks(path, public_jwk(EC_KEY, "ec-1"), public_jwk(RSA_KEY, "rsa-1", use="sig"))


@pytest.fixture
def keyset(tmp_path: Path) -> VehicleKeySet:
    return load_vehicle_jwks(operator_jwks(tmp_path / "jwks.json"))


def assert_refused(keyset: VehicleKeySet, token: Any, audience: str = AUD) -> InvalidVehicleToken:
    with pytest.raises(InvalidVehicleToken) as refused:
        keyset.verify(token, audience, now=NOW)
    error = refused.value
    assert str(error) == INVALID_TOKEN_MESSAGE and error.args == (INVALID_TOKEN_MESSAGE,)
    assert isinstance(error.cause, str) and error.cause
    if isinstance(token, str) and len(token) > 16:
        assert token not in error.cause
    assert error.__cause__ is None  # no PyJWT exception chained into tracebacks
    return error


# -- accepted ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("private", "kid"), [(EC_KEY, "ec-1"), (RSA_KEY, "rsa-1")], ids=["ES256", "RS256"])
def test_valid_tokens_give_the_vehicle_id(keyset, private, kid):
    assert keyset.verify(sign(private, claims(), kid=kid), AUD, now=NOW) == "veh-42"


def test_a_token_without_kid_is_accepted_when_one_key_fits_its_alg(keyset):
    # one EC and one RSA key: each alg has exactly one candidate
    assert keyset.verify(sign(EC_KEY, claims(sub="a")), AUD, now=NOW) == "a"
    assert keyset.verify(sign(RSA_KEY, claims(sub="b")), AUD, now=NOW) == "b"


def test_a_set_without_kids_selects_by_alg(tmp_path):
    keyset = load_vehicle_jwks(write_jwks(tmp_path / "k.json", public_jwk(EC_KEY), public_jwk(RSA_KEY)))
    assert keyset.verify(sign(EC_KEY, claims()), AUD, now=NOW) == "veh-42"
    assert keyset.verify(sign(RSA_KEY, claims()), AUD, now=NOW) == "veh-42"
    assert_refused(keyset, sign(EC_KEY, claims(), kid="ec-1"))  # a kid naming no key


def test_clock_skew_is_tolerated_up_to_the_constant(keyset):
    skew = int(CLOCK_SKEW_S)
    ok = [claims(exp=NOW - skew + 1), claims(nbf=NOW + skew), claims(iat=NOW + skew), claims(exp=NOW + 0.5)]
    for payload in ok:
        assert keyset.verify(sign(EC_KEY, payload, kid="ec-1"), AUD, now=NOW) == "veh-42"
    for payload in [claims(exp=NOW - skew), claims(nbf=NOW + skew + 1), claims(iat=NOW + skew + 1)]:
        assert_refused(keyset, sign(EC_KEY, payload, kid="ec-1"))


def test_now_is_the_verification_time(keyset):
    token = sign(EC_KEY, claims(nbf=NOW, exp=NOW + 60), kid="ec-1")
    assert keyset.verify(token, AUD, now=NOW + 30) == "veh-42"
    with pytest.raises(InvalidVehicleToken):
        keyset.verify(token, AUD, now=NOW + 60 + CLOCK_SKEW_S)  # expired later
    with pytest.raises(InvalidVehicleToken):
        keyset.verify(token, AUD, now=NOW - CLOCK_SKEW_S - 1)  # not yet valid before


def test_audience_is_configurable_and_may_be_one_of_a_list(keyset):
    assert keyset.verify(sign(EC_KEY, claims(aud="fleet-b"), kid="ec-1"), "fleet-b", now=NOW) == "veh-42"
    assert keyset.verify(sign(EC_KEY, claims(aud=["x", AUD]), kid="ec-1"), AUD, now=NOW) == "veh-42"
    assert_refused(keyset, sign(EC_KEY, claims(), kid="ec-1"), audience="fleet-b")


def test_longest_sub_is_accepted(keyset):
    sub = "v" * MAX_SUB_LENGTH
    assert keyset.verify(sign(EC_KEY, claims(sub=sub), kid="ec-1"), AUD, now=NOW) == sub


def test_keys_for_other_uses_are_left_out_and_listed(tmp_path):
    path = write_jwks(
        tmp_path / "k.json",
        public_jwk(EC_KEY, "ec-1", use="sig", alg="ES256", key_ops=["verify"]),
        public_jwk(EC_KEY_2, "ec-enc", use="enc"),
        public_jwk(RSA_KEY, "rsa-ps", alg="PS256"),
        public_jwk(RSA_ATTACKER, "rsa-wrap", key_ops=["wrapKey"]),
    )
    keyset = load_vehicle_jwks(path)
    assert [key.kid for key in keyset.keys] == ["ec-1"] and len(keyset.ignored) == 3
    assert keyset.verify(sign(EC_KEY, claims(), kid="ec-1"), AUD, now=NOW) == "veh-42"
    # a key that is not for signatures does not verify, by kid or as the only key of its type
    assert_refused(keyset, sign(EC_KEY_2, claims(), kid="ec-enc"))
    assert_refused(keyset, sign(RSA_KEY, claims(), kid="rsa-ps"))
    assert_refused(keyset, sign(RSA_KEY, claims(), kid="rsa-ps", alg="PS256"))
    assert_refused(keyset, sign(RSA_KEY, claims()))


# -- refused -----------------------------------------------------------------------------------------


def _none_token() -> str:
    return jwt.encode(claims(), None, algorithm="none", headers={"kid": "ec-1"})


REFUSED = {
    "expired": lambda: sign(EC_KEY, claims(exp=NOW - 3600), kid="ec-1"),
    "expired RS256": lambda: sign(RSA_KEY, claims(exp=NOW - 3600), kid="rsa-1"),
    "not yet valid": lambda: sign(EC_KEY, claims(nbf=NOW + 3600), kid="ec-1"),
    "issued in the future": lambda: sign(EC_KEY, claims(iat=NOW + 3600), kid="ec-1"),
    "wrong aud": lambda: sign(EC_KEY, claims(aud="another-service"), kid="ec-1"),
    "aud list without us": lambda: sign(EC_KEY, claims(aud=["a", "b"]), kid="ec-1"),
    "no aud": lambda: sign(EC_KEY, claims(aud=None), kid="ec-1"),
    "no exp": lambda: sign(EC_KEY, claims(exp=None), kid="ec-1"),
    "exp not a number": lambda: sign(EC_KEY, claims(exp=str(NOW + 300)), kid="ec-1"),
    "exp true": lambda: sign(EC_KEY, claims(exp=True), kid="ec-1"),
    "nbf not a number": lambda: sign(EC_KEY, claims(nbf="soon"), kid="ec-1"),
    "no sub": lambda: sign(EC_KEY, claims(sub=None), kid="ec-1"),
    "empty sub": lambda: sign(EC_KEY, claims(sub=""), kid="ec-1"),
    "sub not a string": lambda: sign(EC_KEY, claims(sub=42), kid="ec-1"),
    "sub too long": lambda: sign(EC_KEY, claims(sub="v" * (MAX_SUB_LENGTH + 1)), kid="ec-1"),
    "sub with a newline": lambda: sign(EC_KEY, claims(sub="veh\n42"), kid="ec-1"),
    "alg none": _none_token,
    "alg none without kid": lambda: jwt.encode(claims(), None, algorithm="none"),
    "alg None spelled differently": lambda: f"{b64json({'alg': 'NONE', 'kid': 'ec-1'})}.{b64json(claims())}.",
    "HS256 with the RSA public PEM": lambda: hand_signed(
        {"alg": "HS256", "kid": "rsa-1", "typ": "JWT"}, claims(), public_pem(RSA_KEY)
    ),
    "HS256 with the RSA public PEM, no kid": lambda: hand_signed(
        {"alg": "HS256", "typ": "JWT"}, claims(), public_pem(RSA_KEY)
    ),
    "HS256 with the EC public PEM": lambda: hand_signed(
        {"alg": "HS256", "kid": "ec-1", "typ": "JWT"}, claims(), public_pem(EC_KEY)
    ),
    "HS384 with the RSA JWK as secret": lambda: hand_signed(
        {"alg": "HS384", "kid": "rsa-1"},
        claims(),
        json.dumps(public_jwk(RSA_KEY, "rsa-1")).encode(),
        "sha384",
    ),
    "another EC key with the same kid": lambda: sign(EC_ATTACKER, claims(), kid="ec-1"),
    "another RSA key with the same kid": lambda: sign(RSA_ATTACKER, claims(), kid="rsa-1"),
    "ES256 token naming the RSA key": lambda: sign(EC_ATTACKER, claims(), kid="rsa-1"),
    "PS256 by the genuine RSA key": lambda: sign(RSA_KEY, claims(), alg="PS256", kid="rsa-1"),
    "ES384": lambda: sign(EC384_ATTACKER, claims(), alg="ES384", kid="ec-1"),
    "unknown kid": lambda: sign(EC_KEY, claims(), kid="ec-2"),
    "kid not a string": lambda: raw_signed({"alg": "ES256", "kid": 7}, claims(), EC_KEY),
    "tampered payload, original signature": lambda: _tampered(),
    "padded signature": lambda: sign(EC_KEY, claims(), kid="ec-1") + "==",
    "trailing whitespace": lambda: sign(EC_KEY, claims(), kid="ec-1") + " ",
    "a fourth segment": lambda: sign(EC_KEY, claims(), kid="ec-1") + ".e30",
    "empty string": lambda: "",
    "not a string": lambda: None,
    "bytes": lambda: sign(EC_KEY, claims(), kid="ec-1").encode(),
    "huge": lambda: "a" * 100_000,
    **{
        f"garbage {text!r}": (lambda text=text: text)
        for text in [
            "garbage",
            "a.b.c",
            "..",
            "...",
            "e30.e30.",
            "e30.e30.e30",
            "Bearer x.y.z",
            "nul\x00l",
            "é.é.é",
            "eyJhbGciOiJFUzI1NiJ9",
            "W10.e30.",
            "bnVsbA.e30.",
            "eyJhbGciOiJFUzI1NiJ9.W10.AA",
        ]
    },
}


def _tampered() -> str:
    header, _, signature = sign(EC_KEY, claims(), kid="ec-1").split(".")
    return f"{header}.{b64json(claims(sub='veh-43'))}.{signature}"


@pytest.mark.parametrize("make", REFUSED.values(), ids=REFUSED.keys())
def test_refused_with_one_message(keyset, make):
    assert_refused(keyset, make())


def test_no_kid_is_refused_when_two_keys_fit_its_alg(tmp_path):
    path = write_jwks(tmp_path / "k.json", public_jwk(EC_KEY, "a"), public_jwk(EC_KEY_2, "b"))
    keyset = load_vehicle_jwks(path)
    assert keyset.verify(sign(EC_KEY_2, claims(), kid="b"), AUD, now=NOW) == "veh-42"
    assert_refused(keyset, sign(EC_KEY, claims()))
    assert_refused(keyset, sign(EC_KEY_2, claims()))


def test_causes_tell_the_refusals_apart(keyset):
    names = ["expired", "wrong aud", "no exp", "alg none", "unknown kid"]
    names.append("tampered payload, original signature")
    causes = {name: assert_refused(keyset, REFUSED[name]()).cause for name in names}
    assert len(set(causes.values())) == len(causes), causes


def test_an_empty_audience_or_a_nan_time_is_a_caller_bug(keyset):
    with pytest.raises(ValueError):
        keyset.verify(sign(EC_KEY, claims(aud=""), kid="ec-1"), "", now=NOW)
    with pytest.raises(ValueError):  # NaN would compare false with every exp
        keyset.verify(sign(EC_KEY, claims(exp=NOW - 3600), kid="ec-1"), AUD, now=float("nan"))


# -- JWKS files --------------------------------------------------------------------------------------


def _rsa_1024() -> dict[str, Any]:
    return public_jwk(rsa.generate_private_key(public_exponent=65537, key_size=1024), "small")


BAD_JWKS = {
    "bad JSON": lambda: '{"keys": [',
    "not UTF-8": lambda: b"\xff\xfe{}",
    "a list": lambda: "[]",
    "no keys": lambda: '{"kty": "EC"}',
    "keys not a list": lambda: '{"keys": {"kty": "EC"}}',
    "empty keys": lambda: '{"keys": []}',
    "a member not an object": lambda: {"keys": [public_jwk(EC_KEY, "ec-1"), "ec-2"]},
    "private EC key": lambda: {"keys": [private_jwk(EC_KEY, "ec-1")]},
    "private RSA key": lambda: {"keys": [public_jwk(EC_KEY, "ec-1"), private_jwk(RSA_KEY, "rsa-1")]},
    "private RSA key marked enc": lambda: {
        "keys": [public_jwk(EC_KEY, "e"), {**private_jwk(RSA_KEY, "r"), "use": "enc"}]
    },
    "RSA 1024": lambda: {"keys": [public_jwk(EC_KEY, "ec-1"), _rsa_1024()]},
    "oct key": lambda: {"keys": [{"kty": "oct", "k": b64(b"s" * 32), "kid": "h"}]},
    "OKP key": lambda: {"keys": [{"kty": "OKP", "crv": "Ed25519", "x": b64(b"x" * 32)}]},
    "no kty": lambda: {"keys": [{"x": "y"}]},
    "EC P-384": lambda: {"keys": [public_jwk(EC384_ATTACKER, "p384")]},
    "EC point not on the curve": lambda: {"keys": [{**public_jwk(EC_KEY, "ec-1"), "y": b64(b"\x01" * 32)}]},
    "EC coordinate not a string": lambda: {"keys": [{**public_jwk(EC_KEY, "ec-1"), "x": 5}]},
    "RSA without n": lambda: {"keys": [{"kty": "RSA", "e": "AQAB"}]},
    "kid not a string": lambda: {"keys": [{**public_jwk(EC_KEY), "kid": 5}]},
    "two keys with one kid": lambda: {"keys": [public_jwk(EC_KEY, "k"), public_jwk(RSA_KEY, "k")]},
    "only keys for other uses": lambda: {"keys": [public_jwk(EC_KEY, "ec-1", use="enc")]},
}


@pytest.mark.parametrize("content", BAD_JWKS.values(), ids=BAD_JWKS.keys())
def test_unusable_jwks_is_an_error_naming_the_file(tmp_path, content):
    path = tmp_path / "operator-jwks.json"
    value = content()
    if isinstance(value, bytes):
        path.write_bytes(value)
    else:
        path.write_text(value if isinstance(value, str) else json.dumps(value))
    with pytest.raises(JwksError, match="operator-jwks.json"):
        load_vehicle_jwks(path)


def test_missing_jwks_file_is_an_error_naming_it(tmp_path):
    with pytest.raises(JwksError, match="nowhere.json.*cannot read"):
        load_vehicle_jwks(tmp_path / "nowhere.json")
    with pytest.raises(JwksError, match="cannot read"):
        load_vehicle_jwks(tmp_path)  # a directory


def test_private_keys_are_refused_with_the_reason(tmp_path):
    path = write_jwks(tmp_path / "k.json", private_jwk(EC_KEY, "ec-1"))
    with pytest.raises(JwksError, match="private key.*public keys only"):
        load_vehicle_jwks(path)


def test_small_rsa_keys_are_refused_with_the_reason(tmp_path):
    with pytest.raises(JwksError, match="1024 bits, at least 2048"):
        load_vehicle_jwks(write_jwks(tmp_path / "k.json", _rsa_1024()))


# -- property: forgeries of valid tokens -------------------------------------------------------------

B64_ALPHABET = string.ascii_letters + string.digits + "-_"
FORGED_ALGS = ["none", "HS256", "HS384", "RS256", "ES256", "PS256", "ES384"]
GENUINE = {
    "ES256": sign(EC_KEY, claims(sub="veh-ec"), kid="ec-1"),
    "RS256": sign(RSA_KEY, claims(sub="veh-rs"), kid="rsa-1"),
}
VALID = {token: json.loads(base64url_decode(token.split(".")[1]))["sub"] for token in GENUINE.values()}
PUBLIC_PEMS = {"ec-1": public_pem(EC_KEY), "rsa-1": public_pem(RSA_KEY)}
ATTACKER_KEYS = {"RS256": RSA_ATTACKER, "PS256": RSA_ATTACKER, "ES256": EC_ATTACKER, "ES384": EC384_ATTACKER}

segment = st.integers(0, 2)
replace = st.tuples(
    st.just("replace"), segment, st.integers(0, 10_000), st.sampled_from(B64_ALPHABET + ".=+/ \x00é")
)
bitflip = st.tuples(st.just("bitflip"), segment, st.integers(0, 100_000))
swap = st.tuples(st.just("swap"), segment, segment)
header_edit = st.tuples(
    st.just("header"),
    st.sampled_from(FORGED_ALGS),
    st.sampled_from(["keep", "drop", "ec-1", "rsa-1", "unknown", 7]),  # kid
    st.sampled_from(["keep", "empty", "confusion", "attacker"]),  # signature
)
claim_value = st.one_of(
    st.just("keep"),
    st.just("drop"),
    st.text(max_size=MAX_SUB_LENGTH + 10),
    st.integers(NOW - 10_000, NOW + 10_000),
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([None, True, [], ["edgepos"], [AUD, "x"], "edgepos", "veh-ec", "veh-rs"]),
)
payload_edit = st.tuples(
    st.just("payload"),
    st.fixed_dictionaries({"sub": claim_value, "aud": claim_value, "exp": claim_value, "nbf": claim_value}),
)
mutation = st.one_of(replace, bitflip, swap, header_edit, payload_edit)


def _resign(header: dict[str, Any], payload_segment: str, signature: str, how: str) -> str:
    header_segment = b64json(header, sort_keys=True)
    signing_input = f"{header_segment}.{payload_segment}".encode()
    alg, kid = header["alg"], header.get("kid")
    if how == "empty":
        signature = ""
    elif how == "confusion" and alg.startswith("HS"):  # HMAC keyed with a genuine public key's PEM
        pem = PUBLIC_PEMS.get(kid) if isinstance(kid, str) else None
        secret = pem or PUBLIC_PEMS["rsa-1"]
        digest = hashlib.sha256 if alg == "HS256" else hashlib.sha384
        signature = b64(hmac.new(secret, signing_input, digest).digest())
    elif how == "confusion" and alg == "PS256":  # the genuine RSA key, under an algorithm not allowed
        signature = b64(jwt.get_algorithm_by_name("PS256").sign(signing_input, RSA_KEY))
    elif how == "attacker":
        algorithm = jwt.get_algorithm_by_name(alg)
        key = ATTACKER_KEYS.get(alg, b"attacker secret")
        signature = b64(algorithm.sign(signing_input, key)) if alg != "none" else ""
    return f"{header_segment}.{payload_segment}.{signature}"


def apply(token: str, edit: tuple[Any, ...]) -> str:
    parts = token.split(".")
    while len(parts) < 3:  # earlier edits may have put dots anywhere
        parts.append("")
    parts = [parts[0], parts[1], ".".join(parts[2:])]
    kind = edit[0]
    if kind == "replace":
        _, index, position, char = edit
        text = parts[index]
        if text:
            position %= len(text)
            parts[index] = text[:position] + char + text[position + 1 :]
        else:
            parts[index] = char
    elif kind == "bitflip":
        _, index, bit = edit
        try:
            data = bytearray(base64url_decode(parts[index]))
        except Exception:  # noqa: BLE001 - an earlier edit broke the segment's base64
            return token
        if data:
            bit %= 8 * len(data)
            data[bit // 8] ^= 1 << (bit % 8)
            parts[index] = b64(bytes(data))
    elif kind == "swap":
        _, first, second = edit
        parts[first], parts[second] = parts[second], parts[first]
    elif kind == "header":
        _, alg, kid, how = edit
        try:
            header = json.loads(base64url_decode(parts[0]))
            assert isinstance(header, dict)
        except Exception:  # noqa: BLE001 - a garbled header of a forged token is replaced, whatever broke
            header = {"typ": "JWT"}
        header["alg"] = alg
        if kid == "drop":
            header.pop("kid", None)
        elif kid != "keep":
            header["kid"] = kid
        return _resign(header, parts[1], parts[2], how)
    elif kind == "payload":
        try:
            payload = json.loads(base64url_decode(parts[1]))
            assert isinstance(payload, dict)
        except Exception:  # noqa: BLE001 - a garbled payload of a forged token is replaced, whatever broke
            payload = {}
        for name, value in edit[1].items():
            if value == "drop":
                payload.pop(name, None)
            elif value != "keep":
                payload[name] = value
        parts[1] = b64json(payload)  # same encoding as jwt.encode: unchanged claims give the same bytes
    return ".".join(parts)


@pytest.fixture(scope="module")
def operator_keyset(tmp_path_factory: pytest.TempPathFactory) -> VehicleKeySet:
    """One key set for all examples (a module fixture: hypothesis runs the test body many times)."""
    return load_vehicle_jwks(operator_jwks(tmp_path_factory.mktemp("jwks") / "jwks.json"))


def test_the_property_keyset_accepts_the_originals(operator_keyset):
    for token, sub in VALID.items():
        assert operator_keyset.verify(token, AUD, now=NOW) == sub


@settings(max_examples=300, deadline=None)
@given(original=st.sampled_from(sorted(GENUINE)), edits=st.lists(mutation, min_size=1, max_size=3))
def test_forgeries_are_refused_unless_byte_identical_to_a_valid_token(operator_keyset, original, edits):
    forged = GENUINE[original]
    for edit in edits:
        forged = apply(forged, edit)
    try:
        sub = operator_keyset.verify(forged, AUD, now=NOW)
    except InvalidVehicleToken as error:
        assert str(error) == INVALID_TOKEN_MESSAGE and error.cause
        assert len(forged) < 16 or forged not in error.cause
    else:
        assert forged in VALID, f"accepted a forgery: {forged!r}"
        assert sub == VALID[forged]
