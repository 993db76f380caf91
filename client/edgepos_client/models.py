"""Typed models of the edgepos wire contract v1 (the client's own copies, independent of the server).

Units are SI and angles radians throughout; positions are in the site-local east-north plane in
metres (x east, y north) and angles counter-clockwise from east. Request models refuse NaN and
infinity (the server would too); response models ignore fields they do not know, so a newer server
that adds fields keeps working with this client.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class _Response(BaseModel):
    model_config = ConfigDict(extra="ignore")


# -- RSUs -----------------------------------------------------------------------------------------
class Rsu(BaseModel):
    """A roadside unit at (x, y) m in the site frame, with optional noise and radius overrides.

    Used both ways (sent by PUT, read by GET), so unknown fields of a newer server are ignored."""

    model_config = ConfigDict(extra="ignore", allow_inf_nan=False, frozen=True)

    id: str = Field(pattern=r"^[A-Za-z0-9._:+-]{1,64}$", description="RSU identifier.")
    x: float = Field(description="East coordinate (m).")
    y: float = Field(description="North coordinate (m).")
    range_std: float | None = Field(None, gt=0, description="Range noise 1-sigma (m); null: session option.")
    bearing_std: float | None = Field(
        None, gt=0, description="Bearing noise 1-sigma (rad); null: session option."
    )
    radius: float | None = Field(None, gt=0, description="Communication radius (m); null: session option.")


# -- measurements ---------------------------------------------------------------------------------
class RsuMeasurement(_Request):
    """Range (m) and bearing (rad, from the RSU to the vehicle, CCW from east) reported by one RSU."""

    type: Literal["rsu"] = "rsu"
    t: float = Field(description="Time (s, vehicle clock); equal t means one epoch.")
    rsu_id: str = Field(description="Id of a registered RSU.")
    range: float = Field(ge=0, description="Distance RSU -> vehicle (m).")
    bearing: float = Field(
        ge=-math.pi, le=math.pi, description="Direction RSU -> vehicle (rad, CCW from east)."
    )


class GyroMeasurement(_Request):
    """Yaw rate (rad/s, CCW positive) of the vehicle's gyro."""

    type: Literal["gyro"] = "gyro"
    t: float = Field(description="Time (s, vehicle clock); equal t means one epoch.")
    yaw_rate: float = Field(description="Yaw rate (rad/s, counter-clockwise positive).")


class PseudorangeMeasurement(_Request):
    """One satellite's code pseudorange and C/N0 for the gnss_tight pipeline.

    ``t`` is the receive time as GPS time of week (s). The server computes the satellite's position and
    clock from the ephemerides loaded with ``put_ephemerides`` unless both ``sat_position`` (ECEF WGS-84 m
    at transmit time, in the Earth-fixed frame of the transmit epoch) and ``sat_clock`` (s, corrected
    range = pseudorange_m + c * sat_clock) are given."""

    type: Literal["pseudorange"] = "pseudorange"
    t: float = Field(ge=0.0, lt=604800.0, description="GPS time of week (s); equal t means one epoch.")
    system: Literal["G", "C", "E"] = Field(description="G GPS, C BeiDou, E Galileo (RINEX letters).")
    prn: int = Field(ge=1, le=63, description="Satellite number (PRN) within its constellation.")
    pseudorange_m: float = Field(ge=1.0e6, le=1.0e8, description="Code pseudorange as measured (m).")
    cn0_dbhz: float = Field(ge=0.0, le=100.0, description="Carrier-to-noise density (dB-Hz), 0 if unknown.")
    sat_position: tuple[float, float, float] | None = Field(
        None, description="Satellite ECEF position at transmit time (m); send with sat_clock."
    )
    sat_clock: float | None = Field(
        None, ge=-0.01, le=0.01, description="Satellite clock offset (s); send with sat_position."
    )
    doppler_hz: float | None = Field(
        None,
        ge=-20000.0,
        le=20000.0,
        description="Doppler of the same signal (Hz), RINEX sign: positive when the satellite approaches "
        "(range rate = -doppler_hz x the carrier's wavelength). Optional; gives the server velocity and clock drift.",
    )
    carrier_cycles: float | None = Field(
        None,
        gt=-1.0e10,
        lt=1.0e10,
        description="Carrier phase of the same signal (cycles), RINEX convention (grows with the range). "
        "Optional; the server smooths the pseudorange with it (options.carrier_smoothing).",
    )
    lli: int | None = Field(
        None,
        ge=0,
        le=7,
        description="RINEX loss-of-lock indicator of carrier_cycles (bit 0: lock lost since the previous epoch).",
    )
    sat_velocity: tuple[float, float, float] | None = Field(
        None,
        description="Satellite ECEF velocity at transmit time (m/s, rate of sat_position's Earth-fixed "
        "coordinates); send with sat_position, sat_clock and sat_clock_drift so the server can use doppler_hz.",
    )
    sat_clock_drift: float | None = Field(
        None, ge=-1.0e-6, le=1.0e-6, description="Satellite clock drift (s/s); send with sat_velocity."
    )


class RissMeasurement(_Request):
    """Reduced inertial sample (vehicle frame x forward, y left, z up) for the gnss_tight pipeline."""

    type: Literal["riss"] = "riss"
    t: float = Field(ge=0.0, lt=604800.0, description="GPS time of week (s).")
    wheel_speed: float = Field(ge=-100.0, le=100.0, description="Wheel odometer speed (m/s, < 0 reversing).")
    accel_x: float = Field(ge=-50.0, le=50.0, description="Forward specific force (m/s^2).")
    accel_y: float = Field(ge=-50.0, le=50.0, description="Lateral specific force, positive left (m/s^2).")
    gyro_z: float = Field(ge=-10.0, le=10.0, description="Yaw rate (rad/s, counter-clockwise positive).")


def _exactly_one(first: str, first_value: float | None, second: str, second_value: float | None) -> None:
    if (first_value is None) == (second_value is None):
        state = "both were given" if first_value is not None else "neither was given"
        raise ValueError(f"give exactly one of {first} and {second}; {state}")


class RsuRangeMeasurement(_Request):
    """Range only (m, >= 0) from a registered RSU to the vehicle."""

    type: Literal["rsu_range"] = "rsu_range"
    t: float = Field(description="Time (s, vehicle clock); equal t means one epoch.")
    rsu_id: str = Field(description="Id of a registered RSU.")
    range: float = Field(ge=0, description="Distance RSU -> vehicle (m).")


class GnssFixMeasurement(_Request):
    """A GNSS position solution in the site frame (m), with its 1-sigma per axis when known."""

    type: Literal["gnss_fix"] = "gnss_fix"
    t: float = Field(description="Time (s, vehicle clock); equal t means one epoch.")
    x: float = Field(description="East position (m).")
    y: float = Field(description="North position (m).")
    std: float | None = Field(None, gt=0, description="1-sigma of x and of y (m); null: session option.")


class OdometerMeasurement(_Request):
    """Wheel odometry: exactly one of distance (m since the previous odometer reading) or speed (m/s)."""

    type: Literal["odometer"] = "odometer"
    t: float = Field(description="Time (s, vehicle clock); equal t means one epoch.")
    distance: float | None = Field(None, ge=0, description="Distance since the previous reading (m).")
    speed: float | None = Field(None, ge=0, description="Speed over ground (m/s).")

    @model_validator(mode="after")
    def _one_of(self) -> OdometerMeasurement:
        _exactly_one("distance", self.distance, "speed", self.speed)
        return self


class V2vRangeMeasurement(_Request):
    """Range to a neighbour vehicle, by its vehicle_id: exactly one of range (m) or one-way toa (s)."""

    type: Literal["v2v_range"] = "v2v_range"
    t: float = Field(description="Time (s, vehicle clock); equal t means one epoch.")
    peer_vehicle_id: str = Field(description="The neighbour's vehicle_id.")
    range: float | None = Field(None, ge=0, description="Distance between the vehicles (m).")
    toa: float | None = Field(
        None, ge=0, description="One-way time of arrival (s); the server scales it by c."
    )

    @model_validator(mode="after")
    def _one_of(self) -> V2vRangeMeasurement:
        _exactly_one("range", self.range, "toa", self.toa)
        return self


Measurement = Annotated[
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
MEASUREMENTS = TypeAdapter(list[Measurement])
"""Validates and serialises lists of measurements (dicts are accepted and checked)."""


class InitialState(_Request):
    """A known start in the site frame: position (m) and velocity (m/s) with their 1-sigma."""

    x: float
    y: float
    vx: float
    vy: float
    position_std: float = Field(1.0, gt=0)
    velocity_std: float = Field(1.0, gt=0)


# -- pipelines -------------------------------------------------------------------------------------
class PipelineOption(_Response):
    name: str
    type: str
    default: Any = None
    description: str = ""
    minimum: float | None = None
    maximum: float | None = None
    choices: list[Any] | None = None


class PipelineInfo(_Response):
    name: str
    description: str = ""
    measurement_types: list[str] = Field(default_factory=list)
    options: list[PipelineOption] = Field(default_factory=list)


# -- ephemerides -----------------------------------------------------------------------------------
class GpsTime(_Response):
    """A GPS time as week, seconds of week and seconds since 1980-01-06."""

    week: int
    tow: float
    gps_seconds: float


class EphemeridesSummary(_Response):
    """What the server loaded from a navigation file (``GET /v1/ephemerides``)."""

    digest: str
    size_bytes: int
    uploaded_at: float
    systems: list[str] = Field(default_factory=list)
    satellite_count: int = 0
    satellites: list[str] = Field(default_factory=list)
    records: dict[str, int] = Field(default_factory=dict)
    healthy_records: int = 0
    skipped_records: dict[str, int] = Field(default_factory=dict)
    valid_from: GpsTime | None = None
    valid_until: GpsTime | None = None
    ionosphere: list[str] = Field(default_factory=list)
    klobuchar: bool = False


# -- fixes -----------------------------------------------------------------------------------------
class StateEstimate(_Response):
    """Full state (mean and covariance) in the order of ``components`` (xp, xv, ..., SI units)."""

    components: list[str]
    mean: list[float]
    covariance: list[list[float]]


class MeasurementUse(_Response):
    """Whether measurement ``index`` of the batch entered the filter update, and if not, why."""

    index: int
    type: str
    used: bool
    reason: str | None = None
    doppler_used: bool | None = None  # a pseudorange sent with doppler_hz: whether its Doppler was used
    doppler_reason: str | None = None
    correction_applied: bool | None = None  # a pseudorange of a session with options.base_station
    correction_reason: str | None = None  # why no reference-station correction was added (when not)
    noise_std: float | None = None  # gnss_tight, a pseudorange used: its noise std in the update (m)
    noise_reason: str | None = None  # why: noise model, carrier smoothing, down-weighting over time


FixStatus = Literal["initialised", "tracking", "predicted", "uninitialised", "diverged"]


class Fix(_Response):
    """The estimate after one epoch: site frame (m, m/s, rad, rad/s); kinematics null if uninitialised."""

    t: float
    status: FixStatus
    revised: bool = False
    """True: this epoch was answered before and late measurements changed its estimate; this fix replaces
    the earlier one of the same ``t`` (keep the last fix received for each ``t``)."""
    divergence: str | None = None
    """With status "diverged": which physical bound the estimate broke and what the server did (by
    default the session was reset: keep sending measurements; do not use this fix's position)."""
    x: float | None = None
    y: float | None = None
    vx: float | None = None
    vy: float | None = None
    speed: float | None = None
    heading: float | None = None
    yaw_rate: float | None = None
    latitude: float | None = None
    longitude: float | None = None
    height: float | None = None
    position_covariance: list[list[float]] | None = None
    state: StateEstimate | None = None
    model_probabilities: dict[str, float] = Field(default_factory=dict)
    nis: float | None = None
    nis_dof: int = 0
    constraints: list[str] | None = None
    """gnss_tight: vehicle pseudo-measurements in this epoch's update ("non-holonomic", "zero-velocity")."""
    protection_level_m: float | None = None
    """Horizontal protection level (m) at the session's integrity risk; None when ``integrity`` is
    "unavailable" (and from servers that predate it)."""
    integrity: str = "unavailable"
    """"ok", "alarm" (do not use the fix where integrity matters) or "unavailable"."""
    measurements: list[MeasurementUse] = Field(default_factory=list)


class BatchResult(_Response):
    seq: int
    fixes: list[Fix]


# -- sessions --------------------------------------------------------------------------------------
class SessionCreated(_Response):
    """Answer to opening a session; ``superseded`` is the vehicle's previous live session, which this
    one replaced (its token now gets 409 superseded), or None."""

    session_id: str
    token: str = Field(repr=False)
    vehicle_id: str
    pipeline: str
    options: dict[str, Any] = Field(default_factory=dict)
    created_at: float
    superseded: str | None = None


class SessionInfo(_Response):
    """What ``GET /v1/sessions/{id}`` reports: configuration, counters and the latest fix."""

    session_id: str
    vehicle_id: str
    pipeline: str
    options: dict[str, Any] = Field(default_factory=dict)
    last_seq: int
    batches: int
    epochs: int
    initialised: bool
    t: float | None = None
    model_probabilities: dict[str, float] = Field(default_factory=dict)
    last_fix: Fix | None = None
    created_at: float
    updated_at: float


class FixEvent(_Response):
    """One fix of the fix stream (``GET /v1/stream/fixes``): whose it is, the batch's seq and the fix (its
    ``state`` is always None on the stream). ``id`` resumes the stream after this event."""

    id: str
    session_id: str
    vehicle_id: str
    pipeline: str
    seq: int
    fix: Fix


class StreamNotice(_Response):
    """A ``missed`` event (fixes the stream's buffer no longer held when resuming: ``missed`` of them, None
    when unknown) or an ``end`` event (the server ended the stream: ``slow_consumer``, ``session_ended``)."""

    event: Literal["missed", "end"]
    reason: str
    message: str = ""
    last_event_id: str | None = None
    missed: int | None = None
    oldest_event_id: str | None = None


class Track(_Response):
    """``GET /v1/sessions/{id}/track``: the estimates of the session's lag window, oldest first,
    filtered or (``smoothed``) smoothed over the window."""

    session_id: str
    pipeline: str
    smoothed: bool
    max_delay_s: float
    start_t: float | None = None
    end_t: float | None = None
    fixes: list[Fix] = Field(default_factory=list)


class SessionSummary(_Response):
    """One live session as ``GET /v1/sessions`` lists it (admin): counters and the latest fix's time
    and status (``"new"`` before the first fix)."""

    session_id: str
    vehicle_id: str
    pipeline: str
    created_at: float
    updated_at: float
    last_seq: int = 0
    batches: int = 0
    epochs: int = 0
    last_fix_t: float | None = None
    status: str = "new"


class SessionPage(_Response):
    """A page of live sessions in session-id order; pass ``next_after`` as ``after`` for the next one
    (None on the last page)."""

    sessions: list[SessionSummary] = Field(default_factory=list)
    next_after: str | None = None


# -- vehicle registry ------------------------------------------------------------------------------
VEHICLE_ID_PATTERN = r"^[A-Za-z0-9._:+@/ -]{1,128}$"
"""What the server accepts as a vehicle id: 1-128 letters, digits, space and . _ : + @ / -."""


class Vehicle(_Response):
    """A registered vehicle (never its key); times are Unix seconds on the server's clock."""

    vehicle_id: str
    created_at: float
    key_issued_at: float


class VehicleKey(Vehicle):
    """A vehicle with its newly issued key (starts with ``evk_``): the server shows it once and keeps
    only a hash. Hand it to the vehicle; it opens sessions for that vehicle only."""

    key: str = Field(repr=False)


class VehicleImport(_Response):
    """Result of importing vehicles: those registered now (each with its key) and the ids that were
    registered before, left unchanged (their keys too)."""

    registered: list[VehicleKey] = Field(default_factory=list)
    already_registered: list[str] = Field(default_factory=list)


class VehiclePage(_Response):
    """A page of registered vehicles in id order; ``total`` counts all of them; pass ``next_after`` as
    ``after`` for the next page (None on the last page)."""

    vehicles: list[Vehicle] = Field(default_factory=list)
    total: int = 0
    next_after: str | None = None


class Revocation(_Response):
    """Answer to revoking a vehicle: its key opens nothing any more, and ``ended_session`` is the live
    session that ended with it (None when it had none)."""

    vehicle_id: str
    ended_session: str | None = None


# -- errors ----------------------------------------------------------------------------------------
class Problem(_Response):
    """One reason the server refused a request: measurement index (or null), field path and why."""

    index: int | None = None
    field: str = ""
    reason: str = ""


class ErrorDetail(_Response):
    code: str
    message: str
    problems: list[Problem] = Field(default_factory=list)


class ErrorBody(_Response):
    error: ErrorDetail
