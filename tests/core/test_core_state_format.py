"""edgepos.core.state: bit-exact round trips and refusal of anything it did not write."""

from __future__ import annotations

import json
import struct
import sys

import numpy as np
import pytest
from edgepos.core import state
from edgepos.core.state import StateFormatError, pack, unpack

SPECIAL = np.array(
    [
        0.0,
        -0.0,
        5e-324,
        -5e-324,
        2.2250738585072009e-308,
        sys.float_info.max,
        -sys.float_info.max,
        sys.float_info.min,
        1e308,
        1.0 + 2**-52,
        0.1,
        -1 / 3,
        np.nextafter(0.0, 1.0) * 3,
    ]
)


def finite_bits(rng: np.random.Generator, count: int) -> np.ndarray:
    values = rng.integers(0, 2**64, count, dtype=np.uint64, endpoint=False).view(np.float64)
    return values[np.isfinite(values)]


def sample_arrays(rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "special": SPECIAL.copy(),
        "matrix": rng.normal(0.0, 1e3, (3, 8, 8)),
        "random_bits": finite_bits(rng, 500),
        "empty": np.zeros((0, 8)),
        "single": np.array([-0.0]),
        "fortran": np.asfortranarray(rng.normal(size=(4, 3))),
    }


META = {
    "pipeline": "test",
    "t": 0.1 + 0.2,
    "neg_zero": -0.0,
    "tiny": 5e-324,
    "huge": 1.7976931348623157e308,
    "nested": {"list": [1, 2.5, None, True, "text é"], "empty": {}},
    "epochs": 12,
}


def assert_bit_identical(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape
    assert a.dtype == np.float64 and b.dtype == np.float64
    assert np.array_equal(a, b)
    assert np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes()


def test_round_trip_is_bit_exact() -> None:
    rng = np.random.default_rng(1)
    arrays = sample_arrays(rng)
    blob = pack(META, arrays)
    meta, restored = unpack(blob)
    assert list(restored) == list(arrays)
    for name, array in arrays.items():
        assert_bit_identical(np.asarray(array, dtype=float), restored[name])
    assert meta == META
    assert struct.pack("<d", meta["neg_zero"]) == struct.pack("<d", -0.0)
    assert meta["tiny"] == 5e-324 and meta["huge"] == 1.7976931348623157e308
    assert pack(meta, restored) == blob


def test_zero_dimensional_arrays_keep_their_shape() -> None:
    """A 0-d array (a scalar such as a time or a count) must come back 0-d, not as shape (1,)."""
    _, restored = unpack(pack({}, {"scalar": np.array(-0.0)}))
    assert restored["scalar"].shape == ()
    assert restored["scalar"].tobytes() == np.array(-0.0).tobytes()


def test_negative_zero_and_subnormals_keep_their_bits() -> None:
    arrays = {"x": np.array([-0.0, 0.0, 5e-324, -1e-310])}
    _, restored = unpack(pack({}, arrays))
    assert restored["x"].view(np.uint64).tolist() == arrays["x"].view(np.uint64).tolist()


def test_restored_arrays_are_writable_and_independent_of_the_blob() -> None:
    blob = pack({}, {"x": np.arange(4.0)})
    _, restored = unpack(blob)
    restored["x"][0] = 42.0
    assert unpack(blob)[1]["x"][0] == 0.0


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_arrays_are_refused(bad: float) -> None:
    with pytest.raises(ValueError):
        pack({}, {"x": np.array([1.0, bad])})


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_meta_is_refused(bad: float) -> None:
    with pytest.raises(ValueError):
        pack({"t": bad}, {})


def test_every_truncation_is_a_state_format_error() -> None:
    blob = pack(META, {"a": np.arange(6.0).reshape(2, 3), "b": np.array([-0.0])})
    for length in range(len(blob)):
        with pytest.raises(StateFormatError):
            unpack(blob[:length])


def test_trailing_bytes_are_a_state_format_error() -> None:
    blob = pack(META, {"a": np.arange(3.0)})
    with pytest.raises(StateFormatError):
        unpack(blob + b"\x00")


@pytest.mark.parametrize(
    "mutate",
    [
        pytest.param(lambda b: b"XPST" + b[4:], id="magic"),
        pytest.param(lambda b: b[:4] + bytes([state.VERSION + 1]) + b[5:], id="version"),
        pytest.param(lambda b: b[:5] + struct.pack("<I", 3) + b[9:], id="header-length-short"),
        pytest.param(lambda b: b[:5] + struct.pack("<I", 2**31) + b[9:], id="header-length-huge"),
        pytest.param(lambda b: b[:9] + b"\xff\xfe" + b[11:], id="header-not-utf8"),
        pytest.param(lambda b: b[:9] + b"[" + b[10:], id="header-not-json"),
        pytest.param(lambda b: b"", id="empty"),
        pytest.param(lambda b: b"not a state at all, just some text", id="text"),
    ],
)
def test_corrupt_blobs_are_state_format_errors(mutate) -> None:
    blob = pack(META, {"a": np.arange(3.0)})
    with pytest.raises(StateFormatError):
        unpack(mutate(blob))


def blob_with_header(header: object, payload: bytes = b"\x00" * 24) -> bytes:
    encoded = json.dumps(header).encode()
    return struct.pack("<4sBI", state.MAGIC, state.VERSION, len(encoded)) + encoded + payload


@pytest.mark.parametrize(
    "header",
    [
        pytest.param({"meta": {}}, id="no-arrays-key"),
        pytest.param([1, 2], id="header-is-a-list"),
        pytest.param("text", id="header-is-a-string"),
        pytest.param({"meta": {}, "arrays": 5}, id="arrays-not-a-list"),
        pytest.param({"meta": {}, "arrays": [["x"]]}, id="array-entry-without-shape"),
        pytest.param({"meta": {}, "arrays": [["x", ["a"]]]}, id="shape-not-numbers"),
        pytest.param({"meta": {}, "arrays": [["x", [1.5]]]}, id="shape-not-integers"),
        pytest.param({"meta": {}, "arrays": [["x", [-3]]]}, id="negative-shape"),
        pytest.param({"arrays": [["x", [3]]]}, id="no-meta-key"),
    ],
)
def test_well_formed_json_with_a_wrong_structure_is_a_state_format_error(header: object) -> None:
    """Valid JSON that is not a header this module writes must be refused as a format error,
    not surface as KeyError / TypeError / a bare ValueError."""
    with pytest.raises(StateFormatError):
        unpack(blob_with_header(header))
