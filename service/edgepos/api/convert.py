"""Between the pipelines' dataclasses and the wire models: no arithmetic beyond unit-free copying,
except the optional WGS-84 position, which the pure ``edgepos.geo`` module computes."""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import pydantic_core

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
    written in one ``to_json`` call (a call per fix cost a tenth of the batch's JSON). The list's JSON is cut
    where one fix ends and the next begins; should a fix hold that sequence of bytes elsewhere (no field does
    today), the cuts do not come out one per fix and each fix is written on its own."""
    if not fixes:
        return []
    heads = to_json([_fix_fields(fix, include_state, origin) for fix in fixes])
    cut = heads[1:-2].split(_NEXT_FIX)  # without the list's brackets and the last fix's closing brace
    if len(cut) != len(fixes):
        return [fix_bytes(fix, include_state, origin) for fix in fixes]
    cut[1:] = [b'{"t":' + part for part in cut[1:]]
    return [
        b'%b,"measurements":[%b]}' % (head, b",".join([_use_bytes(u) for u in fix.measurements]))
        for head, fix in zip(cut, fixes, strict=True)
    ]


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
    body = pydantic_core.to_json(value, inf_nan_mode="constants")
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
