"""Between the pipelines' dataclasses and the wire models: no arithmetic beyond unit-free copying,
except the optional WGS-84 position, which the pure ``edgepos.geo`` module computes."""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import pydantic_core
from pydantic_core import CoreConfig, SchemaSerializer, core_schema

from edgepos.api.schemas import OptionOut, PipelineOut, RsuModel, RsuOut
from edgepos.geo import GeodeticOrigin
from edgepos.pipelines.base import Fix, MeasurementUse, Pipeline, Rsu


def rsu_from_wire(rsu: RsuModel) -> Rsu:
    return Rsu(
        id=rsu.id, x=rsu.x, y=rsu.y, range_std=rsu.range_std, bearing_std=rsu.bearing_std, radius=rsu.radius
    )


def rsu_to_wire(rsu: Rsu) -> RsuOut:
    return RsuOut(
        id=rsu.id, x=rsu.x, y=rsu.y, range_std=rsu.range_std, bearing_std=rsu.bearing_std, radius=rsu.radius
    )


def pipeline_to_wire(pipeline: Pipeline) -> PipelineOut:
    return PipelineOut(
        name=pipeline.name,
        description=pipeline.description,
        measurement_types=list(pipeline.measurement_kinds),
        options=[
            OptionOut(
                name=spec.name,
                type=spec.type,
                default=spec.default,
                description=spec.description,
                minimum=spec.minimum,
                maximum=spec.maximum,
                choices=None if spec.choices is None else list(spec.choices),
            )
            for spec in pipeline.option_specs()
        ],
        smoother=pipeline.smoother,
    )


def fix_to_json(fix: Fix, include_state: bool, origin: GeodeticOrigin | None) -> dict[str, Any]:
    """The wire fix: :class:`FixOut`'s fields, in its order, as plain JSON values (``state`` only when
    asked for). Latitude, longitude and height are the pipeline's own when it estimates a global position
    (gnss_tight); otherwise latitude/longitude of (x, y) on the site's tangent plane when an origin is
    configured. Plain values rather than the response models: building and validating a FixOut and its
    measurement uses cost three times the JSON writing itself (a test checks the shape against FixOut)."""
    return {
        **_fix_fields(fix, include_state, origin),
        "measurements": [_use_to_json(u) for u in fix.measurements],
    }


def fix_bytes(fix: Fix, include_state: bool, origin: GeodeticOrigin | None) -> bytes:
    """``to_json(fix_to_json(fix, include_state, origin))``, the very bytes, with each measurement use's
    JSON written once per use object (``_use_bytes``): a batch's uses are mostly the same few immutable
    records (``pipelines.rsu_imu_run.used``), and writing them was half of a fix's JSON."""
    head = to_json(_fix_fields(fix, include_state, origin))  # "measurements" comes last: spliced in
    return b'%b,"measurements":[%b]}' % (head[:-1], b",".join([_use_bytes(u) for u in fix.measurements]))


_NEXT_FIX = b'},{"t":'
"""Where one fix's fields end and the next one's begin in the JSON of a list of them: ``t`` comes first."""


def fixes_bytes(fixes: Sequence[Fix], include_state: bool, origin: GeodeticOrigin | None) -> list[bytes]:
    """``[fix_bytes(fix, include_state, origin) for fix in fixes]``, the very bytes, with every fix's fields
    read and written by pydantic-core in one call (:data:`_FIX_HEADS`: no dict per fix, the keys written in
    Rust; the fields' dicts and their writing were two thirds of the batch's JSON), and each fix's uses
    joined once per sequence of use objects (:func:`_uses_bytes`). The list's JSON is cut where one fix ends
    and the next begins; should a fix hold that sequence of bytes elsewhere (no field does today), the cuts
    do not come out one per fix and each fix is written on its own. With a site origin and a fix whose
    latitude comes from it, the fields are the dicts of :func:`_fix_fields`."""
    if not fixes:
        return []
    if origin is not None and any(
        fix.latitude is None and fix.x is not None and fix.y is not None for fix in fixes
    ):
        heads = to_json([_fix_fields(fix, include_state, origin) for fix in fixes])
    else:
        heads = _checked(_FIX_HEADS[include_state].to_json(fixes, by_alias=True, warnings="error"))
    # without the list's bracket and the first fix's '{"t":', and the last fix's closing brace and bracket
    cut = heads[6:-2].split(_NEXT_FIX)
    if len(cut) != len(fixes):
        return [fix_bytes(fix, include_state, origin) for fix in fixes]
    return [
        b'{"t":%b,"measurements":[%b]}' % (head, _uses_bytes(fix.measurements))
        for head, fix in zip(cut, fixes, strict=True)
    ]


def _state(fix: Fix, _: object) -> dict[str, Any] | None:
    """The wire fix's ``state`` when asked for (:func:`_fix_fields`')."""
    if fix.state is None or fix.state_cov is None:
        return None
    return {"components": list(fix.state_components), "mean": fix.state, "covariance": fix.state_cov}


def _fix_heads(include_state: bool) -> SchemaSerializer:
    """A serializer of a list of fixes writing :func:`_fix_fields`' JSON of each (no site origin) straight
    from the :class:`Fix` dataclass: its fields read by name in the wire order, renamed by alias, each
    value written as ``to_json`` infers it (``any``), so the bytes are those of the fields' dicts."""
    written_as = core_schema.any_schema()
    state = core_schema.any_schema(
        serialization=core_schema.plain_serializer_function_ser_schema(
            _state if include_state else lambda *_: None, is_field_serializer=True
        )
    )
    wire = {"position_cov": "position_covariance", "protection_level": "protection_level_m"}
    names = [
        *("t", "status", "revised", "divergence", "x", "y", "vx", "vy", "speed", "heading", "yaw_rate"),
        *("latitude", "longitude", "height", "position_cov", "state", "model_probabilities", "nis"),
        *("nis_dof", "constraints", "protection_level", "integrity"),
    ]
    fields = [
        core_schema.dataclass_field(
            name, state if name == "state" else written_as, serialization_alias=wire.get(name, name)
        )
        for name in names
    ]
    fix = core_schema.dataclass_schema(Fix, core_schema.dataclass_args_schema("Fix", fields), names)
    return SchemaSerializer(core_schema.list_schema(fix), CoreConfig(ser_json_inf_nan="constants"))


#: The fixes' fields' serializers without and with the state.
_FIX_HEADS = {False: _fix_heads(False), True: _fix_heads(True)}


def _fix_fields(fix: Fix, include_state: bool, origin: GeodeticOrigin | None) -> dict[str, Any]:
    """:func:`fix_to_json` without its last field, the measurement uses."""
    latitude, longitude, height = fix.latitude, fix.longitude, fix.height
    if latitude is None and origin is not None and fix.x is not None and fix.y is not None:
        latitude, longitude, _ = origin.enu_to_geodetic(fix.x, fix.y, 0.0)
    state = None
    if include_state and fix.state is not None and fix.state_cov is not None:
        state = {"components": list(fix.state_components), "mean": fix.state, "covariance": fix.state_cov}
    return {
        "t": fix.t,
        "status": fix.status,
        "revised": fix.revised,
        "divergence": fix.divergence,
        "x": fix.x,
        "y": fix.y,
        "vx": fix.vx,
        "vy": fix.vy,
        "speed": fix.speed,
        "heading": fix.heading,
        "yaw_rate": fix.yaw_rate,
        "latitude": latitude,
        "longitude": longitude,
        "height": height,
        "position_covariance": fix.position_cov,
        "state": state,
        "model_probabilities": fix.model_probabilities,
        "nis": fix.nis,
        "nis_dof": fix.nis_dof,
        "constraints": None if fix.constraints is None else list(fix.constraints),
        "protection_level_m": fix.protection_level,
        "integrity": fix.integrity,
    }


#: Measurement uses' JSON by the use object's id, with the object (kept alive, so its id is not reused).
_USE_BYTES: dict[int, tuple[MeasurementUse, bytes]] = {}
_USE_BYTES_LIMIT = 4096  # then the table starts afresh: uses made per fix (gnss_tight's) only pass through


#: A fix's uses' JSON joined, by the uses' ids, with the uses (kept alive: no other object can hold their
#: ids while the entry lives, so equal ids are the very same frozen uses).
_USES_BYTES: dict[tuple[int, ...], tuple[tuple[MeasurementUse, ...], bytes]] = {}
_USES_BYTES_LIMIT = 1024  # then the table starts afresh


def _uses_bytes(uses: Sequence[MeasurementUse]) -> bytes:
    """The JSON of a fix's uses, comma-joined: written once per sequence of use objects. A batch's fixes
    take theirs from the same shared records batch after batch (``pipelines.rsu_imu_run.used_records``),
    so one lookup per fix replaces one per use (14 → 6 µs a 20-fix batch)."""
    key = tuple(map(id, uses))
    entry = _USES_BYTES.get(key)
    if entry is not None:
        return entry[1]
    written = b",".join([_use_bytes(u) for u in uses])
    if len(_USES_BYTES) >= _USES_BYTES_LIMIT:
        _USES_BYTES.clear()
    _USES_BYTES[key] = (tuple(uses), written)
    return written


def _use_bytes(use: MeasurementUse) -> bytes:
    """``to_json(_use_to_json(use))``, written once per use object (uses are frozen)."""
    entry = _USE_BYTES.get(id(use))
    if entry is not None and entry[0] is use:
        return entry[1]
    written = to_json(_use_to_json(use))
    if len(_USE_BYTES) >= _USE_BYTES_LIMIT:
        _USE_BYTES.clear()
    _USE_BYTES[id(use)] = (use, written)
    return written


def _use_to_json(use: MeasurementUse) -> dict[str, Any]:
    """One measurement's use (the Doppler fields null unless it is a pseudorange that carried a Doppler; the
    correction fields null unless the session uses a reference station's corrections)."""
    return {
        "index": use.index,
        "type": use.kind,
        "used": use.used,
        "reason": use.reason,
        "doppler_used": use.doppler_used,
        "doppler_reason": use.doppler_reason,
        "correction_applied": use.correction_applied,
        "correction_reason": use.correction_reason,
        "noise_std": use.noise_std,
        "noise_reason": use.noise_reason,
    }


# A number in value position (after ':', ',' or '[' in compact JSON) that JSON cannot hold.
_NON_FINITE = re.compile(rb"[:,\[]-?(?:NaN|Infinity)")


def to_json(value: Any) -> bytes:
    """Compact JSON of plain values (``fix_to_json``'s); ValueError on NaN or infinity, which the
    response models refuse as well (``ResponseModel``: floats are always finite)."""
    return _checked(pydantic_core.to_json(value, inf_nan_mode="constants"))


def _checked(body: bytes) -> bytes:
    """:func:`to_json`'s body, refused (ValueError) if it holds NaN or infinity as a number."""
    # Cheapest first: a byte search for the capitals of NaN and Infinity (memchr; a fix's JSON seldom has
    # either), then the substrings (a tenth of the time of the pattern), then the pattern, which confirms.
    if (
        (b"N" in body or b"I" in body)
        and (b"NaN" in body or b"Infinity" in body)
        and _NON_FINITE.search(body)
    ):
        raise ValueError("a fix holds a non-finite number")
    return body


def joined_batch_body(seq: int, fixes: Sequence[bytes]) -> bytes:
    """The :class:`BatchOut` JSON joined from each fix's compact JSON (:func:`to_json`): the very bytes of
    ``to_json({"seq": seq, "fixes": [...]})``, so that a fix written once serves the answer, its fix
    event and the session's last fix."""
    return b'{"seq":%d,"fixes":[%b]}' % (int(seq), b",".join(fixes))
