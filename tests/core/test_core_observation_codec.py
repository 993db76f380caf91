"""The binary observation codec: exact round trips for every kind and field shape, and clear errors for
bytes it did not write."""

from __future__ import annotations

import dataclasses
import math
import struct
import typing
from collections.abc import Sequence

import pytest
from edgepos.core.observation_codec import (
    ObservationCodecError,
    _field_form,
    _KindCodec,
    decode_legacy_observations,
    decode_observations,
    encode_each,
    encode_observations,
)
from edgepos.core.observations import (
    GyroObservation,
    Observation,
    PseudorangeObservation,
    PseudorangeObservationV2,
    RsuObservation,
    V2vRangeObservation,
)
from hypothesis import given, settings
from hypothesis import strategies as st

finite = st.floats(allow_nan=False, allow_infinity=False)
anything_float = st.floats(allow_nan=False)  # infinities are bits like any other
text = st.text(max_size=12)


def _bits(value: object) -> object:
    """Floats by their bits (so -0.0 and 0.0 differ), tuples element by element."""
    if isinstance(value, float):
        return struct.pack("<d", value)
    if isinstance(value, tuple):
        return tuple(_bits(v) for v in value)
    return value


def _same(decoded: Sequence[Observation], original: Sequence[Observation]) -> bool:
    return [type(o) for o in decoded] == [type(o) for o in original] and [
        tuple(_bits(getattr(o, f.name)) for f in dataclasses.fields(o)) for o in decoded
    ] == [tuple(_bits(getattr(o, f.name)) for f in dataclasses.fields(o)) for o in original]


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.builds(RsuObservation, anything_float, text, anything_float, anything_float),
            st.builds(GyroObservation, anything_float, anything_float),
            st.builds(
                V2vRangeObservation, finite, text, st.none() | anything_float, st.none() | anything_float
            ),
            st.builds(
                PseudorangeObservation,
                finite,
                st.sampled_from(["G", "C", "E", "R"]),
                st.integers(-(2**63), 2**63 - 1),
                finite,
                finite,
                st.none() | st.tuples(finite, finite, finite),
                st.none() | finite,
                st.none() | anything_float,
            ),
        ),
        max_size=12,
    )
)
def test_any_epoch_round_trips_bit_for_bit(observations):
    decoded = decode_observations(encode_observations(observations))
    assert _same(decoded, observations)


def test_every_kind_has_a_codec_and_none_falls_back_to_json():
    """The codec is derived from the dataclass fields: nothing of the current kinds needs the JSON
    fallback, so a new kind or field of a plain type is written as numbers and text."""
    for cls in typing.get_args(Observation):
        hints = typing.get_type_hints(cls)
        forms = {_field_form(hints[field.name])[0] for field in dataclasses.fields(cls)}
        assert "j" not in forms, cls


def test_a_field_of_another_type_goes_through_json_and_comes_back_as_tuples():
    @dataclasses.dataclass(frozen=True)
    class Odd:
        kind: typing.ClassVar[str] = "odd"
        t: float
        extra: dict[str, list[int]] | None
        flags: tuple[int, ...]
        ok: bool

    codec = _KindCodec(Odd)
    for value in (Odd(1.0, {"a": [1, 2]}, (1, 2), True), Odd(-0.0, None, (), False)):
        record = codec.encode(value)
        decoded, end = codec.decode(record, 1 + len(b"odd"))
        assert decoded == value and end == len(record)
        assert math.copysign(1.0, decoded.t) == math.copysign(1.0, value.t)


def test_an_epoch_of_the_paper_scenario_is_compact():
    epoch = [RsuObservation(0.3, f"S+{k}00", 40.0 + k, 0.1 * k) for k in range(4)] + [
        GyroObservation(0.3, 0.01)
    ]
    record = encode_observations(epoch)
    # per RSU: kind (1 + 3), t, range, bearing (3 x 8), the id (2 + 5); the gyro: kind (1 + 4), t, rate
    assert len(record) == 4 * (4 + 24 + 2 + 5) + (5 + 16)


@pytest.mark.parametrize(
    "record",
    [
        b"\x07teleport" + b"\x00" * 16,  # unknown kind
        b"\x04gyro" + b"\x00" * 15,  # a float short
        b"\x03rsu" + b"\x00" * 24 + b"\x09\x00abc",  # text longer than what follows
        b"\x04gyro" + b"\x00" * 16 + b"\x04",  # a second observation cut short
        b"\x03rsu" + b"\x00" * 24 + b"\x02\x00\xff\xfe",  # text that is not UTF-8
        b"\xff",
    ],
)
def test_bytes_it_did_not_write_are_a_codec_error(record):
    with pytest.raises(ObservationCodecError):
        decode_observations(record)


def test_every_cut_of_a_real_record_is_a_codec_error():
    record = encode_observations(
        [
            RsuObservation(1.5, "S+000", 12.25, -3.0),
            PseudorangeObservation(1.5, "C", 30, 2.4e7, 39.0, (1.0, 2.0, 3.0)),
        ]
    )
    first = len(encode_observations([RsuObservation(1.5, "S+000", 12.25, -3.0)]))
    for cut in range(1, len(record)):
        if cut == first:
            assert len(decode_observations(record[:cut])) == 1  # a whole first observation is a record
            continue
        with pytest.raises(ObservationCodecError):
            decode_observations(record[:cut])
    assert decode_observations(b"") == []


def test_version_2_records_read_as_todays_observations_without_doppler():
    """A lag window of version 2 stored pseudoranges before doppler_hz existed: its records decode through the
    old layout into today's observations (doppler_hz None), the other kinds unchanged; today's codec would
    misread them, which is why the window's version changed."""
    old = _KindCodec(PseudorangeObservationV2)
    gyro = GyroObservation(1.5, -0.25)
    pseudoranges = [
        PseudorangeObservationV2(1.5, "G", 7, 2.1e7, 44.5),
        PseudorangeObservationV2(1.5, "C", 30, 2.4e7, 39.0, (-1.2e7, 1.5e7, 2.1e7), 1.2e-5),
    ]
    record = encode_observations([gyro]) + b"".join(old.encode(o) for o in pseudoranges)
    decoded = decode_legacy_observations(record, 2)
    assert decoded == [gyro] + [o.current() for o in pseudoranges]
    assert all(o.doppler_hz is None for o in decoded[1:]) and isinstance(decoded[1], PseudorangeObservation)
    with pytest.raises(ObservationCodecError):
        decode_observations(record)  # the new layout is 8 bytes longer per pseudorange
    with pytest.raises(ObservationCodecError):
        decode_legacy_observations(record, 1)
    with_doppler = PseudorangeObservation(1.5, "E", 3, 2.3e7, 41.0, doppler_hz=-1234.5)
    assert decode_observations(encode_observations([with_doppler])) == [with_doppler]


def test_carrier_phase_round_trips_and_plain_pseudoranges_keep_the_stored_layout():
    """carrier_cycles / lli were added without a new lag-window version: a pseudorange without them is written
    in the version-3 layout (so records stored before read back unchanged), one with them under its own name."""
    from edgepos.core.observations import PseudorangeObservationV3

    old = _KindCodec(PseudorangeObservationV3)
    plain = PseudorangeObservation(1.5, "E", 3, 2.3e7, 41.0, None, None, -1234.5)
    carrying = PseudorangeObservation(1.5, "G", 7, 2.1e7, 44.5, None, None, 812.25, 1.1e8 + 0.123, 1)
    phase_only = PseudorangeObservation(1.5, "C", 21, 2.2e7, 40.0, carrier_cycles=-9.9e9)
    assert encode_observations([plain]) == old.encode(
        PseudorangeObservationV3(1.5, "E", 3, 2.3e7, 41.0, None, None, -1234.5)
    )
    record = encode_observations([plain, carrying, phase_only])
    decoded = decode_observations(record)
    assert decoded == [plain, carrying, phase_only]
    assert all(type(o) is PseudorangeObservation for o in decoded)
    assert decoded[1].lli == 1 and decoded[2].lli is None


def test_a_clients_satellite_velocity_round_trips_and_older_carrier_records_read_unchanged():
    """sat_velocity / sat_clock_drift were added without a new lag-window version: a pseudorange without them
    is written as before (plain or ``pseudorange+carrier``), so records stored before read back unchanged; one
    with them is written whole under its own name."""
    from edgepos.core.observations import PseudorangeObservationV4

    carrier_before = _KindCodec(PseudorangeObservationV4, name=b"pseudorange+carrier")
    carrying = PseudorangeObservation(1.5, "G", 7, 2.1e7, 44.5, None, None, 812.25, 1.1e8 + 0.123, 1)
    assert encode_observations([carrying]) == carrier_before.encode(
        PseudorangeObservationV4(1.5, "G", 7, 2.1e7, 44.5, None, None, 812.25, 1.1e8 + 0.123, 1)
    )
    moving = PseudorangeObservation(
        1.5,
        "C",
        21,
        2.2e7,
        40.0,
        (1.0e7, -2.0e7, 1.5e7),
        1e-4,
        -812.5,
        None,
        None,
        (-2231.9, 372.5, -0.0),
        1.5e-12,
    )
    velocity_only_drift = dataclasses.replace(moving, sat_velocity=None)
    record = encode_observations([carrying, moving, velocity_only_drift])
    decoded = decode_observations(record)
    assert decoded == [carrying, moving, velocity_only_drift]
    assert all(type(o) is PseudorangeObservation for o in decoded)
    assert math.copysign(1.0, decoded[1].sat_velocity[2]) == -1.0
    assert b"pseudorange+rate" in record


@pytest.mark.parametrize("kept", [0, 4096])
def test_a_text_is_written_alike_from_the_table_of_texts_or_not(monkeypatch, kept):
    """An id's bytes (16-bit length, UTF-8) are the same the first time, from ``_TEXTS`` after, and with the
    table full (``TEXTS_KEPT``: nothing kept); ``encode_each`` gives each observation's part of the record."""
    from edgepos.core import observation_codec

    monkeypatch.setattr(observation_codec, "_TEXTS", {})
    monkeypatch.setattr(observation_codec, "TEXTS_KEPT", kept)
    epoch = [
        RsuObservation(1.5, "rsu-ü", 12.0, -0.5),
        GyroObservation(1.5, 0.01),
        RsuObservation(1.5, "rsu-ü", 3.0, 0.0),
    ]
    raw = "rsu-ü".encode()
    expected = b"\x03rsu" + struct.pack("<ddd", 1.5, 12.0, -0.5) + struct.pack("<H", len(raw)) + raw
    first, second = encode_observations(epoch), encode_observations(epoch)
    assert first == second and first.startswith(expected)
    assert len(observation_codec._TEXTS) == min(kept, 1)
    assert b"".join(encode_each(epoch)) == first and encode_each(epoch)[0] == expected
    assert _same(decode_observations(first), epoch)
