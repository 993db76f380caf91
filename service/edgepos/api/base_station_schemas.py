"""Wire models of the reference-station resource (``/v1/base-stations``)."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import ConfigDict, Field

from edgepos.api.schemas import GpsTimeOut, RequestModel, ResponseModel

BASE_STATION_ID_PATTERN = r"^[A-Za-z0-9._:+-]{1,64}$"
_EARTH_RADIUS_BOUNDS_M = (6.3e6, 6.4e6)
"""An antenna on the ground is 6.357-6.378 Mm from the Earth's centre; a few km of height is allowed."""


class GeodeticIn(RequestModel):
    """A WGS-84 position in the API's angle unit (radians, as every latitude on the wire)."""

    latitude: float = Field(
        ge=-math.pi / 2, le=math.pi / 2, description="WGS-84 latitude (rad, north positive)."
    )
    longitude: float = Field(ge=-math.pi, le=math.pi, description="WGS-84 longitude (rad, east positive).")
    height: float = Field(ge=-500.0, le=9000.0, description="Ellipsoidal height (m, WGS-84).")


class AntennaDeltaIn(RequestModel):
    """RINEX ``ANTENNA: DELTA H/E/N``: the antenna reference point relative to the marker (m)."""

    up: float = Field(
        ge=-100.0, le=100.0, description="Height of the antenna reference point above the marker (m)."
    )
    east: float = Field(0.0, ge=-100.0, le=100.0, description="East offset (m).")
    north: float = Field(0.0, ge=-100.0, le=100.0, description="North offset (m).")


class BaseStationIn(RequestModel):
    """Body of POST /v1/base-stations. The surveyed position is of the marker; with ``antenna_delta`` the
    corrections use the antenna reference point (the pseudoranges refer to the antenna). At most one of
    ``position_ecef`` and ``position_geodetic``; with neither, an RTCM 1005/1006 message may set it later."""

    model_config = ConfigDict(
        json_schema_extra={
            # at most one of the two positions (the other absent or null), as the route refuses both
            "not": {
                "required": ["position_ecef", "position_geodetic"],
                "properties": {"position_ecef": {"type": "array"}, "position_geodetic": {"type": "object"}},
            },
            "examples": [
                {
                    "station_id": "BASE1",
                    "position_geodetic": {"latitude": 0.8527, "longitude": 0.2008, "height": 120.0},
                    "antenna_delta": {"up": 1.5},
                }
            ],
        }
    )

    station_id: str = Field(
        pattern=BASE_STATION_ID_PATTERN,
        description="Station identifier: 1-64 characters of A-Z a-z 0-9 . _ : + -.",
    )
    position_ecef: list[float] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="Surveyed marker position, Earth-centred Earth-fixed (WGS-84 / ITRF) x, y, z (m); its "
        "distance from the Earth's centre must be 6300-6400 km (a station on the ground), else 422.",
    )
    position_geodetic: GeodeticIn | None = Field(
        None, description="The same position as WGS-84 latitude, longitude, height."
    )
    antenna_delta: AntennaDeltaIn | None = Field(
        None, description="Antenna reference point offset from the marker."
    )
    galileo_group_delay: Literal["broadcast", "none"] = Field(
        "broadcast",
        description="What the station receiver's Galileo E1 code carries of the satellite's group delay, "
        "for its corrections' satellite clocks. broadcast: the Galileo ICD's model (the clock less the BGD "
        "of the navigation record's clock pair); none: the clock without it, for a receiver whose Galileo "
        "code measures as if the satellite had none (gnss_tight's galileo_group_delay says the same of a "
        "vehicle's receiver). Applies to the observations uploaded after registration.",
    )


class BaseStationOut(ResponseModel):
    """A registered reference station."""

    station_id: str = Field(description="Station identifier.")
    position_ecef: list[float] | None = Field(
        description="Antenna reference point the corrections are computed at: ECEF x, y, z (m); null when the "
        "station has no position yet."
    )
    latitude: float | None = Field(
        description="The same point's WGS-84 latitude (rad); null without a position."
    )
    longitude: float | None = Field(
        description="WGS-84 longitude (rad, east positive); null without a position."
    )
    height: float | None = Field(description="Ellipsoidal height (m); null without a position.")
    marker_ecef: list[float] | None = Field(
        description="The marker position as registered (ECEF m), or null."
    )
    antenna_delta: list[float] | None = Field(description="Antenna delta up, east, north (m), or null.")
    position_source: str | None = Field(
        description="Where the position came from: 'registered', 'rtcm 1005' or 'rtcm 1006'; null without one."
    )
    galileo_group_delay: Literal["broadcast", "none"] = Field(
        description="The station receiver's Galileo group delay, as registered (broadcast for stations "
        "registered before the field existed)."
    )
    updated_at: float = Field(description="Last change of the registration (Unix s, server clock).")
    newest_epoch: GpsTimeOut | None = Field(
        description="Time of the newest base epoch with corrections, or null."
    )
    newest_epoch_satellites: int | None = Field(description="Satellites corrected at that epoch, or null.")


class BaseStationList(ResponseModel):
    stations: list[BaseStationOut] = Field(description="Every registered station, sorted by id.")


class BaseObservationsOut(ResponseModel):
    """What an upload of base observations (RINEX 3 or RTCM 3) added to the station's correction window."""

    station_id: str = Field(description="Station identifier.")
    epochs_read: int = Field(
        description="Observation epochs in the upload (GPS, BeiDou and Galileo signals)."
    )
    epochs_stored: int = Field(
        description="Of those, epochs with corrections (at least two satellites of a system above the 10 deg "
        "mask with an ephemeris valid at that time), added to the window."
    )
    corrections: int = Field(description="Satellite corrections stored (summed over the epochs).")
    first_epoch: GpsTimeOut | None = Field(description="First stored epoch, or null.")
    last_epoch: GpsTimeOut | None = Field(description="Last stored epoch, or null.")
    window_epochs: int | None = Field(
        description="Epochs the station's window holds after the upload (the newest EDGEPOS_BASE_WINDOW_EPOCHS); "
        "null when the upload added none (an RTCM upload of only a station position)."
    )
    messages: dict[str, int] | None = Field(
        None,
        description="RTCM uploads: frames read by message type (e.g. {'1077': 300, '1005': 1}); else null.",
    )
    position_set: bool = Field(
        False,
        description="Whether a 1005/1006 message of this upload set the station's position (it had none).",
    )


def valid_ecef(position: list[float]) -> str | None:
    """Why an ECEF position is not one of an antenna on the ground, or None."""
    if not all(math.isfinite(v) for v in position):
        return "must be three finite coordinates (m)"
    radius = math.sqrt(sum(v * v for v in position))
    low, high = _EARTH_RADIUS_BOUNDS_M
    if not low <= radius <= high:
        return f"is {radius:.0f} m from the Earth's centre; a station on the ground is {low:.0f}-{high:.0f} m (ECEF, m)"
    return None
