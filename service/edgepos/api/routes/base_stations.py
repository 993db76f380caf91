"""The site's GNSS reference stations: registration with a surveyed position, base observations (a RINEX 3
observation file, or RTCM 3 MSM4/MSM7 frames) turned into differential corrections shared through the store,
which gnss_tight sessions use with the ``base_station`` option. Writes need the admin key; reads any valid
credential."""

from __future__ import annotations

import logging
import math
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, Path, Request, Response

from edgepos.api.auth import require_admin, require_any
from edgepos.api.base_station_schemas import (
    BASE_STATION_ID_PATTERN,
    BaseObservationsOut,
    BaseStationIn,
    BaseStationList,
    BaseStationOut,
    valid_ecef,
)
from edgepos.api.base_stations import (
    ObservationFileError,
    Station,
    corrections_of,
    epoch_document,
    epoch_of,
    marker_from_geodetic,
    parse_observations,
)
from edgepos.api.context import Context
from edgepos.api.ephemerides import NavigationFileError, _gps_time, decode_upload
from edgepos.api.errors import ApiError
from edgepos.api.routes import errors, json_body
from edgepos.api.schemas import ProblemModel
from edgepos.geo import ecef_to_geodetic
from edgepos.gnss.differential import MAX_AGE_BOUNDS_S, EpochCorrections
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.rinex_obs import ObservationEpoch
from edgepos.gnss.rtcm import RtcmError, decode

logger = logging.getLogger("edgepos.api")

PATH = "/v1/base-stations"
router = APIRouter(prefix=PATH, tags=["base-stations"])

StationId = Annotated[
    str,
    Path(
        pattern=BASE_STATION_ID_PATTERN,
        description="Station identifier (1-64 characters of A-Z a-z 0-9 . _ : + -).",
    ),
]

_RINEX_BODY = {
    "requestBody": {
        "required": True,
        "description": "A RINEX 3 observation file of the station (GPS C1C, BeiDou C2I and Galileo C1C "
        "pseudoranges are used), at most EDGEPOS_MAX_BASE_OBSERVATIONS_BYTES.",
        "content": {
            "text/plain": {"schema": {"type": "string"}},
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}
_RTCM_BODY = {
    "requestBody": {
        "required": True,
        "description": "RTCM 3 frames back to back: MSM4/MSM7 of GPS (1074/1077), Galileo (1094/1097) and "
        "BeiDou (1124/1127); GLONASS, SBAS, QZSS and NavIC MSMs and descriptor, ephemeris and bias messages "
        "are skipped; 1005/1006 set the station's position when it has none; other types are refused. MSM "
        "epoch times are times of week: the week is the one nearest the "
        "loaded ephemerides. At most EDGEPOS_MAX_BASE_OBSERVATIONS_BYTES.",
        "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
    }
}


def _out(station: Station, newest: EpochCorrections | None) -> BaseStationOut:
    position = station.position_ecef
    lat = lon = height = None
    if position is not None:
        lat, lon, height = ecef_to_geodetic(*(float(v) for v in position))
    return BaseStationOut(
        station_id=station.station_id,
        position_ecef=None if position is None else [float(v) for v in position],
        latitude=lat,
        longitude=lon,
        height=height,
        marker_ecef=None if station.marker_ecef is None else list(station.marker_ecef),
        antenna_delta=None if station.antenna_delta is None else list(station.antenna_delta),
        position_source=station.position_source,
        galileo_group_delay=station.galileo_group_delay,
        updated_at=station.updated_at,
        newest_epoch=None if newest is None else _gps_time(newest.gpst),
        newest_epoch_satellites=None if newest is None else len(newest.sats),
    )


async def _station_out(context: Context, station: Station) -> BaseStationOut:
    window = await context.store.base_window(station.station_id, math.inf, math.inf)
    newest = epoch_of(window.epochs[-1][1]) if window is not None and window.epochs else None
    return _out(station, newest)


async def _registered(context: Context, station_id: str) -> Station:
    stored = await context.store.get_base_station(station_id)
    if stored is None:
        raise ApiError("not_found", f"no base station {station_id!r} is registered (POST {PATH})")
    return Station.of(stored)


@router.post(
    "",
    status_code=201,
    response_model=BaseStationOut,
    summary="Register a reference station",
    dependencies=[Depends(require_admin), Depends(json_body)],
    responses=errors(401, 403, 409, 413, 415, 422, 503),
)
async def register_base_station(body: BaseStationIn, context: Context) -> BaseStationOut:
    """Register a station (admin key) with its surveyed marker position (ECEF or WGS-84) and optional antenna
    delta, or without a position (an RTCM 1005/1006 upload may set it). 409 when the id is taken."""
    if body.position_ecef is not None and body.position_geodetic is not None:
        reason = "give position_ecef or position_geodetic, not both"
        raise ApiError(
            "invalid_request", reason, [ProblemModel(index=None, field="position_geodetic", reason=reason)]
        )
    marker = None
    if body.position_ecef is not None:
        why = valid_ecef(body.position_ecef)
        if why is not None:
            raise ApiError(
                "invalid_request",
                f"position_ecef {why}",
                [ProblemModel(index=None, field="position_ecef", reason=why)],
            )
        marker = (float(body.position_ecef[0]), float(body.position_ecef[1]), float(body.position_ecef[2]))
    elif body.position_geodetic is not None:
        g = body.position_geodetic
        marker = marker_from_geodetic(g.latitude, g.longitude, g.height)
    delta = (
        None
        if body.antenna_delta is None
        else (body.antenna_delta.up, body.antenna_delta.east, body.antenna_delta.north)
    )
    station = Station(
        body.station_id,
        marker,
        delta,
        None if marker is None else "registered",
        context.store.clock(),
        body.galileo_group_delay,
    )
    if not await context.store.add_base_station(station.stored()):
        raise ApiError(
            "conflict", f"base station {body.station_id!r} is already registered (DELETE it first)"
        )
    logger.info(
        "base station registered", extra={"event": "base_station_registered", "station": body.station_id}
    )
    return _out(station, None)


@router.get(
    "",
    response_model=BaseStationList,
    summary="List the reference stations",
    dependencies=[Depends(require_any)],
    responses=errors(401, 429, 503),
)
async def list_stations(context: Context) -> BaseStationList:
    """Every registered station, sorted by id, with its newest corrected epoch."""
    stations = [Station.of(stored) for stored in await context.store.list_base_stations()]
    return BaseStationList(stations=[await _station_out(context, station) for station in stations])


@router.get(
    "/{station_id}",
    response_model=BaseStationOut,
    summary="One reference station",
    dependencies=[Depends(require_any)],
    responses=errors(401, 404, 422, 429, 503),
)
async def get_station(station_id: StationId, context: Context) -> BaseStationOut:
    return await _station_out(context, await _registered(context, station_id))


@router.delete(
    "/{station_id}",
    status_code=204,
    response_class=Response,
    summary="Remove a reference station and its corrections",
    dependencies=[Depends(require_admin)],
    responses=errors(401, 403, 404, 422, 503),
)
async def delete_station(station_id: StationId, context: Context) -> Response:
    """Sessions that named it get no corrections from then on (each pseudorange says why)."""
    if not await context.store.delete_base_station(station_id):
        raise ApiError("not_found", f"no base station {station_id!r} is registered")
    logger.info("base station removed", extra={"event": "base_station_removed", "station": station_id})
    return Response(status_code=204)


async def _store_epochs(
    context: Context,
    station: Station,
    epochs: list[ObservationEpoch],
    ephemerides: Ephemerides,
    field: str,
    write_station: bool = False,
) -> tuple[list[EpochCorrections], int]:
    """Compute and store the corrections (and, with ``write_station``, the station's new registration
    first); every refusal comes before any write, so it leaves the station as it was."""
    position = station.position_ecef
    if position is None:
        reason = (
            f"base station {station.station_id!r} has no position: register it with position_ecef or "
            "position_geodetic, or send an RTCM 1005/1006 message"
        )
        raise ApiError(
            "invalid_request", reason, [ProblemModel(index=None, field="station_id", reason=reason)]
        )
    corrections = await context.run_filter(
        corrections_of, epochs, np.asarray(position), ephemerides, station.galileo_group_delay
    )
    if not corrections:
        reason = (
            f"none of the {len(epochs)} epochs has corrections: no GPS, BeiDou or Galileo satellites with an "
            "ephemeris valid at their time above the 10 deg mask (check GET /v1/ephemerides)"
        )
        raise ApiError("invalid_request", reason, [ProblemModel(index=None, field=field, reason=reason)])
    window = await context.store.base_window(station.station_id, math.inf, math.inf)
    if window is not None and window.epochs:
        newest_stored = window.epochs[-1][0]
        limit = MAX_AGE_BOUNDS_S[1]
        if corrections[-1].gpst < newest_stored - limit:
            reason = (
                f"the upload's newest epoch is {newest_stored - corrections[-1].gpst:.0f} s older than the "
                f"station's newest, beyond the largest correction age a session may allow ({limit:g} s): no "
                "rover epoch at the station's present could use it; nothing was stored"
            )
            raise ApiError("invalid_request", reason, [ProblemModel(index=None, field=field, reason=reason)])
    if write_station and not await context.store.replace_base_station(station.stored()):
        raise ApiError("not_found", f"base station {station.station_id!r} was removed during the upload")
    size = await context.store.add_base_epochs(
        station.station_id,
        [(c.gpst, epoch_document(c)) for c in corrections],
        context.settings.base_window_epochs,
    )
    if size is None:
        raise ApiError("not_found", f"base station {station.station_id!r} was removed during the upload")
    return corrections, size


def _answer(
    station: Station, epochs: int, corrections: list[EpochCorrections], size: int
) -> BaseObservationsOut:
    return BaseObservationsOut(
        station_id=station.station_id,
        epochs_read=epochs,
        epochs_stored=len(corrections),
        corrections=sum(len(c.sats) for c in corrections),
        first_epoch=_gps_time(corrections[0].gpst),
        last_epoch=_gps_time(corrections[-1].gpst),
        window_epochs=size,
    )


async def _ephemerides(context: Context) -> Ephemerides:
    loaded = await context.ephemerides.current(context.store, context.run_filter)
    if loaded is None:
        raise ApiError(
            "invalid_request",
            "no ephemerides are loaded (PUT /v1/ephemerides): corrections need the broadcast orbits; the "
            "station is unchanged",
        )
    return loaded.ephemerides


@router.post(
    "/{station_id}/observations",
    response_model=BaseObservationsOut,
    summary="Add base observations (RINEX 3 observation file)",
    dependencies=[Depends(require_admin)],
    responses=errors(401, 403, 404, 413, 422, 503),
    openapi_extra=_RINEX_BODY,
)
async def post_observations(station_id: StationId, request: Request, context: Context) -> BaseObservationsOut:
    """Corrections of every epoch of the file, computed at the station's position with the loaded
    ephemerides, added to the station's window (admin key). A malformed file is refused with its line;
    without loaded ephemerides (PUT /v1/ephemerides) any file is refused (422)."""
    station = await _registered(context, station_id)
    ephemerides = await _ephemerides(context)
    body = await request.body()
    try:
        text = decode_upload(body)
        epochs = await context.run_filter(parse_observations, text)
    except (NavigationFileError, ObservationFileError) as error:
        field = "body" if error.line is None else f"body.line[{error.line}]"
        where = "" if error.line is None else f" at line {error.line}"
        raise ApiError(
            "invalid_request",
            f"not a usable RINEX 3 observation file{where}: {error.reason}; the station is unchanged",
            [ProblemModel(index=None, field=field, reason=error.reason)],
        ) from None
    if not epochs:
        reason = "the file has no epoch with a GPS C1C, BeiDou C2I or Galileo C1C pseudorange"
        raise ApiError("invalid_request", reason, [ProblemModel(index=None, field="body", reason=reason)])
    corrections, size = await _store_epochs(context, station, epochs, ephemerides, "body")
    return _answer(station, len(epochs), corrections, size)


@router.post(
    "/{station_id}/rtcm",
    response_model=BaseObservationsOut,
    summary="Add base observations (RTCM 3 MSM4/MSM7 frames)",
    dependencies=[Depends(require_admin)],
    responses=errors(401, 403, 404, 413, 422, 503),
    openapi_extra=_RTCM_BODY,
)
async def post_rtcm(station_id: StationId, request: Request, context: Context) -> BaseObservationsOut:
    """Decode the frames with pyrtcm and add the corrections of their epochs (admin key). A frame that does
    not parse is refused naming its index, message type and bytes, and nothing is stored. Without loaded
    ephemerides (PUT /v1/ephemerides) any frames are refused (422)."""
    station = await _registered(context, station_id)
    ephemerides = await _ephemerides(context)
    body = await request.body()
    try:
        content = await context.run_filter(decode, body, ephemerides.gpst)
    except RtcmError as error:
        raise ApiError(
            "invalid_request",
            f"RTCM {error.message} does not parse: {error.reason}; the station is unchanged",
            [ProblemModel(index=None, field=f"body.{error.message}", reason=error.reason)],
        ) from None
    position_set = False
    if content.position is not None and station.marker_ecef is None:
        why = valid_ecef(list(content.position))
        if why is not None:
            raise ApiError("invalid_request", f"the RTCM station position {why}")
        kind = "1006" if content.counts.get("1006") else "1005"
        station = Station(
            station.station_id,
            content.position,
            None,
            f"rtcm {kind}",
            context.store.clock(),
            station.galileo_group_delay,
        )
        position_set = True
    if not content.epochs:
        if not position_set:
            reason = (
                "the frames hold no GPS, Galileo or BeiDou MSM4/MSM7 observations and no station position"
            )
            raise ApiError("invalid_request", reason, [ProblemModel(index=None, field="body", reason=reason)])
        if not await context.store.replace_base_station(station.stored()):
            raise ApiError("not_found", f"base station {station_id!r} was removed during the upload")
        return BaseObservationsOut(
            station_id=station_id,
            epochs_read=0,
            epochs_stored=0,
            corrections=0,
            first_epoch=None,
            last_epoch=None,
            window_epochs=None,
            messages=dict(content.counts),
            position_set=True,
        )
    corrections, size = await _store_epochs(
        context, station, list(content.epochs), ephemerides, "body", write_station=position_set
    )
    answer = _answer(station, len(content.epochs), corrections, size)
    return answer.model_copy(update={"messages": dict(content.counts), "position_set": position_set})
