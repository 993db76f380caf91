"""Wire schemas of the measurements a batch carries, and of the batch (POST /v1/sessions/{id}/batches).

The conventions of :mod:`edgepos.api.schemas` hold: SI units, radians, the site frame's x east and y
north, seconds. Measurements are a union discriminated by ``type``: a new measurement type is one
more model here (with its ``to_observation``) plus its entry in :data:`MeasurementModel` and
:data:`MEASUREMENT_TYPES`. ``to_observation`` passes the observation's fields by position, in the
dataclass's order: a batch builds about a hundred of them, and keywords cost a fifth more
(``tests/api/test_api_measurements.py`` checks every field by its name).
"""

from __future__ import annotations

import math
from typing import Annotated, ClassVar, Literal

from pydantic import ConfigDict, Field, ValidationInfo, field_validator

from edgepos.api.schemas import (
    HARD_MAX_BATCH,
    MAX_COORDINATE_M,
    MAX_SEQ,
    MAX_TIME_S,
    RSU_ID_PATTERN,
    VEHICLE_ID_PATTERN,
    RequestModel,
    exactly_one_of,
)
from edgepos.core.observations import (
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    PseudorangeObservation,
    RissObservation,
    RsuObservation,
    RsuRangeObservation,
    V2vRangeObservation,
)

_T_DESCRIPTION = (
    "Measurement time (s) on the vehicle's clock (any epoch, monotone per session); "
    "measurements with equal t form one epoch."
)


class RsuMeasurement(RequestModel):
    """Range and bearing from one RSU to the vehicle."""

    type: Literal["rsu"] = Field(description="Discriminator: 'rsu'.")
    t: float = Field(ge=-MAX_TIME_S, le=MAX_TIME_S, description=_T_DESCRIPTION)
    rsu_id: str = Field(pattern=RSU_ID_PATTERN, description="Id of a registered RSU.")
    range: float = Field(
        ge=0, le=MAX_COORDINATE_M, description="Distance from the RSU to the vehicle (m), >= 0."
    )
    bearing: float = Field(
        ge=-math.pi,
        le=math.pi,
        description="Direction from the RSU to the vehicle (rad, CCW from east), in [-pi, pi].",
    )

    def to_observation(self) -> Observation:
        return RsuObservation(self.t, self.rsu_id, self.range, self.bearing)


class GyroMeasurement(RequestModel):
    """Yaw rate from the vehicle's gyro."""

    type: Literal["gyro"] = Field(description="Discriminator: 'gyro'.")
    t: float = Field(ge=-MAX_TIME_S, le=MAX_TIME_S, description=_T_DESCRIPTION)
    yaw_rate: float = Field(ge=-100, le=100, description="Yaw rate (rad/s, counter-clockwise positive).")

    def to_observation(self) -> Observation:
        return GyroObservation(self.t, self.yaw_rate)


SECONDS_PER_WEEK = 604800.0
_TOW_DESCRIPTION = (
    "Measurement time as GPS time of week (s, [0, 604800)): the receiver's receive time; the week comes from "
    "the loaded ephemerides (or the session's gps_week option). Measurements with equal t form one epoch."
)
MAX_PRN = 63
GNSS_SYSTEMS = ("G", "C", "E")
SATELLITE_RADIUS_M = (1.0e7, 5.0e7)
"""Geocentric distances (m) a client-computed satellite position may have (MEO to GEO/IGSO)."""


class PseudorangeMeasurement(RequestModel):
    """One satellite's code pseudorange and C/N0 (gnss_tight pipeline).

    The satellite's position and clock come from the ephemerides loaded with PUT /v1/ephemerides, unless
    the client sends both ``sat_position`` and ``sat_clock`` (then no ephemeris is needed)."""

    WIRE_FIELDS: ClassVar[dict[str, str]] = {"pseudorange": "pseudorange_m", "cn0": "cn0_dbhz"}
    """Core observation field -> wire field, for naming problems found by the pipeline."""

    type: Literal["pseudorange"] = Field(description="Discriminator: 'pseudorange'.")
    t: float = Field(ge=0.0, lt=SECONDS_PER_WEEK, description=_TOW_DESCRIPTION)
    system: Literal["G", "C", "E"] = Field(
        description="Constellation, as the RINEX system letter: G GPS, C BeiDou, E Galileo."
    )
    prn: int = Field(ge=1, le=MAX_PRN, description="Satellite number within its constellation (PRN, 1-63).")
    pseudorange_m: float = Field(
        ge=1.0e6,
        le=1.0e8,
        description="Code pseudorange (m), as the receiver measured it (no corrections applied): GPS L1 C/A, "
        "BeiDou B1I or Galileo E1 (the signal the service assumes for group delay and ionosphere scaling).",
    )
    cn0_dbhz: float = Field(
        ge=0.0, le=100.0, description="Carrier-to-noise density of the signal (dB-Hz), 0 when not known."
    )
    sat_position: list[float] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="Optional satellite position at transmit time computed by the client: [x, y, z] ECEF "
        "WGS-84 (m), expressed in the Earth-fixed frame of the transmit epoch (the service applies the "
        "Earth-rotation correction), 1e7-5e7 m from the Earth's centre. Send it together with sat_clock.",
    )
    sat_clock: float | None = Field(
        None,
        ge=-0.01,
        le=0.01,
        description="Optional satellite clock offset at transmit time (s), relativity and group delay "
        "included, so that the corrected range is pseudorange_m + c * sat_clock. Send it with sat_position.",
    )
    doppler_hz: float | None = Field(
        None,
        ge=-20000.0,
        le=20000.0,
        description="Optional Doppler of the same signal as pseudorange_m (Hz), as the receiver measured it, "
        "RINEX sign convention: positive when the satellite approaches. The service uses the range rate "
        "-doppler_hz x wavelength of the signal's carrier (GPS L1 / Galileo E1 1575.42 MHz, BeiDou B1I "
        "1561.098 MHz) for velocity and receiver clock drift; it needs the satellite's velocity and clock "
        "drift: from the loaded ephemerides, or with sat_position and sat_clock sent, from sat_velocity and "
        "sat_clock_drift (without them it is reported unused). Finite, within +-20000 Hz.",
    )
    carrier_cycles: float | None = Field(
        None,
        gt=-1.0e10,
        lt=1.0e10,
        description="Optional carrier phase of the same signal as pseudorange_m (cycles: GPS L1 / Galileo E1 "
        "wavelength 0.1903 m, BeiDou B1I 0.1920 m), as the receiver measured it, RINEX convention: it grows as "
        "the range grows (changes by about -doppler_hz per second) and carries an arbitrary constant per "
        "continuous lock. With options.carrier_smoothing 'hatch+tdcp' (the default) the service smooths this "
        "satellite's pseudorange with it (Hatch filter) while lock holds and, in sessions without RISS "
        "samples, takes the receiver's displacement between epochs from the phases' changes; 'hatch' smooths "
        "only. Finite, within +-1e10 cycles (the RINEX field's range).",
    )
    lli: int | None = Field(
        None,
        ge=0,
        le=7,
        description="Optional RINEX loss-of-lock indicator of carrier_cycles (0-7, three bits): bit 0 (value "
        "1) set when the receiver lost lock on this signal since its previous epoch, so the phase may have "
        "slipped; the service then restarts this satellite's smoothing (also when its phase disagrees with "
        "its Doppler or its code). Bit 1 (half-cycle ambiguity) and bit 2 are accepted and not used. Omitted "
        "or null: 0.",
    )

    sat_velocity: list[Annotated[float, Field(ge=-1.0e4, le=1.0e4)]] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="Optional satellite velocity at transmit time computed by the client: [vx, vy, vz] (m/s), "
        "the rate of change of sat_position's Earth-fixed coordinates (ECEF WGS-84, the frame of the "
        "transmit epoch), each within +-10000 m/s. Send it with sat_position, sat_clock and "
        "sat_clock_drift; with doppler_hz it lets the service use the Doppler without ephemerides.",
    )
    sat_clock_drift: float | None = Field(
        None,
        ge=-1.0e-6,
        le=1.0e-6,
        description="Optional satellite clock drift at transmit time (s/s), the rate of sat_clock. Send it "
        "with sat_velocity.",
    )

    def to_observation(self) -> Observation:
        position = velocity = None
        if self.sat_position is not None:  # three items: the field's schema holds it to exactly three
            position = (self.sat_position[0], self.sat_position[1], self.sat_position[2])
        if self.sat_velocity is not None:
            velocity = (self.sat_velocity[0], self.sat_velocity[1], self.sat_velocity[2])
        return PseudorangeObservation(
            self.t,
            self.system,
            self.prn,
            self.pseudorange_m,
            self.cn0_dbhz,
            position,
            self.sat_clock,
            self.doppler_hz,
            self.carrier_cycles,
            self.lli,
            velocity,
            self.sat_clock_drift,
        )


class RissMeasurement(RequestModel):
    """A reduced inertial sensor sample: wheel speed, two accelerometers and the yaw gyro (gnss_tight).

    Vehicle frame: x forward, y left, z up. The sample drives the motion model until the next one (or
    until options.riss_timeout); without samples the pipeline runs GNSS-only."""

    WIRE_FIELDS: ClassVar[dict[str, str]] = {}

    type: Literal["riss"] = Field(description="Discriminator: 'riss'.")
    t: float = Field(ge=0.0, lt=SECONDS_PER_WEEK, description=_TOW_DESCRIPTION)
    wheel_speed: float = Field(
        ge=-100.0,
        le=100.0,
        description="Forward speed from the wheel odometer (m/s, negative when reversing).",
    )
    accel_x: float = Field(
        ge=-50.0, le=50.0, description="Forward specific force (m/s^2, vehicle x axis, positive forward)."
    )
    accel_y: float = Field(
        ge=-50.0, le=50.0, description="Lateral specific force (m/s^2, vehicle y axis, positive to the left)."
    )
    gyro_z: float = Field(
        ge=-10.0,
        le=10.0,
        description="Yaw rate about the vehicle's up axis (rad/s, counter-clockwise positive).",
    )

    def to_observation(self) -> Observation:
        return RissObservation(self.t, self.wheel_speed, self.accel_x, self.accel_y, self.gyro_z)


SPEED_OF_LIGHT_M_S = 299_792_458.0
"""c (m/s), by which a v2v_range toa is scaled to metres (the value GNSS uses, exact by definition)."""
MAX_SPEED_M_S = 200.0
MAX_ODOMETER_DISTANCE_M = 1.0e4
MAX_TOA_S = MAX_COORDINATE_M / SPEED_OF_LIGHT_M_S


def _exactly_one(value: float | None, info: ValidationInfo, other: str, this: str) -> float | None:
    """Refuse both or neither of two alternative fields; runs on the later one (``this``), so the
    error names a field of the measurement. Skipped when ``other`` already failed its own check."""
    if other not in info.data:
        return value
    given = [name for name, v in ((other, info.data[other]), (this, value)) if v is not None]
    if len(given) != 1:
        state = "both were given" if given else "neither was given"
        raise ValueError(f"give exactly one of {other} and {this}; {state}")
    return value


class RsuRangeMeasurement(RequestModel):
    """Range only from one registered RSU (a ranging node at a known position) to the vehicle."""

    type: Literal["rsu_range"] = Field(description="Discriminator: 'rsu_range'.")
    t: float = Field(ge=-MAX_TIME_S, le=MAX_TIME_S, description=_T_DESCRIPTION)
    rsu_id: str = Field(pattern=RSU_ID_PATTERN, description="Id of a registered RSU.")
    range: float = Field(
        ge=0,
        le=MAX_COORDINATE_M,
        description="Distance from the RSU antenna to the vehicle (m), finite, >= 0.",
    )

    def to_observation(self) -> Observation:
        return RsuRangeObservation(self.t, self.rsu_id, self.range)


class GnssFixMeasurement(RequestModel):
    """A GNSS receiver's position solution, already projected into the site frame."""

    type: Literal["gnss_fix"] = Field(description="Discriminator: 'gnss_fix'.")
    t: float = Field(ge=-MAX_TIME_S, le=MAX_TIME_S, description=_T_DESCRIPTION)
    x: float = Field(
        ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description="East position in the site frame (m), finite."
    )
    y: float = Field(
        ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description="North position in the site frame (m), finite."
    )
    std: float | None = Field(
        None,
        ge=1.0e-3,
        le=1.0e4,
        description="1-sigma error of each of x and y (m), 1e-3 to 1e4 (a smaller one would make the filter's "
        "covariance singular); null uses the session's GNSS noise option.",
    )

    def to_observation(self) -> Observation:
        return GnssFixObservation(self.t, self.x, self.y, self.std)


class OdometerMeasurement(RequestModel):
    """Wheel odometry: exactly one of distance (since the previous odometer reading) or speed."""

    model_config = ConfigDict(
        json_schema_extra=exactly_one_of("distance", "speed", json_type=("number", "number"))
    )

    type: Literal["odometer"] = Field(description="Discriminator: 'odometer'.")
    t: float = Field(ge=-MAX_TIME_S, le=MAX_TIME_S, description=_T_DESCRIPTION)
    distance: float | None = Field(
        None,
        ge=0,
        le=MAX_ODOMETER_DISTANCE_M,
        description="Distance travelled along the path (m, >= 0) over the interval since this session's "
        "previous odometer reading; exactly one of distance and speed.",
    )
    speed: float | None = Field(
        None,
        ge=0,
        le=MAX_SPEED_M_S,
        validate_default=True,
        description="Speed over ground at t (m/s, >= 0, unsigned); exactly one of distance and speed.",
    )

    @field_validator("speed")
    @classmethod
    def _one_of(cls, value: float | None, info: ValidationInfo) -> float | None:
        return _exactly_one(value, info, "distance", "speed")

    def to_observation(self) -> Observation:
        return OdometerObservation(self.t, self.distance, self.speed)


class V2vRangeMeasurement(RequestModel):
    """Range to a neighbour vehicle (its own session, by vehicle id): metres, or one-way time of arrival."""

    model_config = ConfigDict(
        json_schema_extra=exactly_one_of("range", "toa", json_type=("number", "number"))
    )

    type: Literal["v2v_range"] = Field(description="Discriminator: 'v2v_range'.")
    t: float = Field(ge=-MAX_TIME_S, le=MAX_TIME_S, description=_T_DESCRIPTION)
    peer_vehicle_id: str = Field(
        pattern=VEHICLE_ID_PATTERN,
        description="vehicle_id of the neighbour ranged to (as its session was created with).",
    )
    range: float | None = Field(
        None,
        ge=0,
        le=MAX_COORDINATE_M,
        description="Distance between the two vehicles' antennas (m, >= 0); exactly one of range and toa.",
    )
    toa: float | None = Field(
        None,
        ge=0,
        le=MAX_TOA_S,
        validate_default=True,
        description="One-way time of arrival of the ranging signal (s, >= 0); the pipeline multiplies it "
        f"by c = {SPEED_OF_LIGHT_M_S:.0f} m/s. Exactly one of range and toa.",
    )

    @field_validator("toa")
    @classmethod
    def _one_of(cls, value: float | None, info: ValidationInfo) -> float | None:
        return _exactly_one(value, info, "range", "toa")

    def to_observation(self) -> Observation:
        return V2vRangeObservation(self.t, self.peer_vehicle_id, self.range, self.toa)


MeasurementModel = Annotated[
    RsuMeasurement
    | GyroMeasurement
    | RsuRangeMeasurement
    | GnssFixMeasurement
    | OdometerMeasurement
    | V2vRangeMeasurement
    | PseudorangeMeasurement
    | RissMeasurement,
    Field(discriminator="type"),
]
MEASUREMENT_TYPES: tuple[str, ...] = (
    "rsu",
    "gyro",
    "rsu_range",
    "gnss_fix",
    "odometer",
    "v2v_range",
    "pseudorange",
    "riss",
)
"""The discriminator values of :data:`MeasurementModel` (used to tidy validation error paths)."""


class BatchIn(RequestModel):
    """Body of POST /v1/sessions/{session_id}/batches."""

    model_config = ConfigDict(
        json_schema_extra={
            "description": "Measurements for the session at the path. seq must be the session's last_seq + 1 "
            "(else 409) and RSU ids must be registered (else 422 naming the measurement): rules of the "
            "session's state that JSON Schema cannot state.",
            "examples": [
                {
                    "seq": 1,
                    "measurements": [
                        {"type": "gyro", "t": 0.0, "yaw_rate": 0.0},
                        {"type": "rsu", "t": 0.0, "rsu_id": "S+000", "range": 8.875, "bearing": 1.5708},
                        {"type": "rsu", "t": 0.0, "rsu_id": "N+050", "range": 51.015, "bearing": -2.9418},
                    ],
                }
            ],
        }
    )

    seq: int = Field(
        ge=1, le=MAX_SEQ, description="Batch number: the session's last_seq + 1 (1 for the first)."
    )
    measurements: list[MeasurementModel] = Field(
        min_length=1,
        max_length=HARD_MAX_BATCH,
        description="Measurements of one or more epochs; "
        "at most EDGEPOS_MAX_BATCH_MEASUREMENTS (default 1000).",
    )
    include_state: bool = Field(False, description="Also return each fix's full state mean and covariance.")
