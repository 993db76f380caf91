"""Wire schemas of API v1 (the shapes in docs/service.md and openapi.json).

Conventions for every field: SI units, angles in radians, positions in the site-local east-north
plane in metres (x east, y north), angles counter-clockwise from +x (east), times in seconds.
Request models forbid unknown fields, refuse NaN and infinity, and are strict about JSON types.
The measurements and the batch that carries them are in :mod:`edgepos.api.measurement_schemas`.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

RSU_ID_PATTERN = r"^[A-Za-z0-9._:+-]{1,64}$"
VEHICLE_ID_PATTERN = r"^[A-Za-z0-9._:+@/ -]{1,128}$"
PIPELINE_NAME_PATTERN = r"^[a-z0-9_]{1,64}$"
#: Most options a session's create body may carry: room above the largest pipeline's count (gnss_tight:
#: 69), which a test holds.
MAX_OPTIONS = 128
MAX_COORDINATE_M = 1.0e6
MAX_TIME_S = 1.0e10
MAX_SEQ = 2**53 - 1
HARD_MAX_BATCH = 100_000
"""Absolute cap on measurements per batch; the configured EDGEPOS_MAX_BATCH_MEASUREMENTS is lower."""
MAX_RSUS_PER_REQUEST = 10_000


class RequestModel(BaseModel):
    """Base of request bodies: unknown fields, NaN/Infinity and loose JSON types are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


def exactly_one_of(first: str, second: str, *, json_type: tuple[str, str]) -> dict[str, Any]:
    """JSON Schema for "exactly one of two fields is given, the other absent or null" (``json_type`` are
    their JSON types when given), for a model's ``json_schema_extra``. Written as ``not`` (both or
    neither) rather than ``oneOf``: a ``oneOf`` beside the properties makes client generators
    (openapi-python-client) split the model into partial variants, while ``not`` is left to validators."""
    both = {
        "required": [first, second],
        "properties": {first: {"type": json_type[0]}, second: {"type": json_type[1]}},
    }
    neither = {"properties": {first: {"type": "null"}, second: {"type": "null"}}}
    return {"not": {"anyOf": [both, neither]}}


class ResponseModel(BaseModel):
    """Base of response bodies (floats are always finite)."""

    model_config = ConfigDict(allow_inf_nan=False)


# -- errors --------------------------------------------------------------------------------------
ErrorCode = Literal[
    "invalid_request",
    "unauthorized",
    "forbidden",
    "not_found",
    "method_not_allowed",
    "conflict",
    "superseded",
    "payload_too_large",
    "unsupported_media_type",
    "too_many_sessions",
    "rate_limited",
    "estimation_failed",
    "unavailable",
    "internal_error",
]


class ProblemModel(ResponseModel):
    """One reason a request was refused."""

    index: int | None = Field(
        None,
        description="Index of the offending measurement in the batch (0-based), or null when not about one.",
    )
    field: str = Field(
        description="Path of the offending field, e.g. 'measurements[3].range' or 'options.filter'."
    )
    reason: str = Field(description="Why the value was refused, in words.")


class ErrorDetail(ResponseModel):
    code: ErrorCode = Field(description="Machine-readable error code; the HTTP status is fixed per code.")
    message: str = Field(description="Human-readable sentence describing the error.")
    problems: list[ProblemModel] = Field(
        default_factory=list,
        description="Every problem found (validation errors list all of them); may be empty.",
    )


class ErrorBody(ResponseModel):
    """The body of every 4xx and 5xx response."""

    error: ErrorDetail


# -- RSUs ----------------------------------------------------------------------------------------
_X_DESCRIPTION = "East coordinate of the RSU antenna in the site frame (m)."
_Y_DESCRIPTION = "North coordinate of the RSU antenna in the site frame (m)."
_RANGE_STD = "Range noise standard deviation of this RSU (m); null uses the session's range_std option."
_BEARING_STD = (
    "Bearing noise standard deviation of this RSU (rad); null uses the session's bearing_std option."
)
_RADIUS = "Communication radius of this RSU (m); null uses the session's comm_radius option."


class RsuFields(RequestModel):
    """The RSU's position and optional per-unit noise and radius."""

    x: float = Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description=_X_DESCRIPTION)
    y: float = Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description=_Y_DESCRIPTION)
    range_std: float | None = Field(None, ge=1.0e-4, le=1.0e4, description=_RANGE_STD)
    bearing_std: float | None = Field(None, ge=1.0e-6, le=math.pi, description=_BEARING_STD)
    radius: float | None = Field(None, gt=0, le=MAX_COORDINATE_M, description=_RADIUS)


class RsuModel(RsuFields):
    """A roadside unit of the site's registry."""

    id: str = Field(
        pattern=RSU_ID_PATTERN, description="RSU identifier: 1-64 characters of A-Z a-z 0-9 . _ : + -."
    )


class RsuPut(RsuFields):
    """Body of PUT /v1/rsus/{rsu_id}: the RSU; ``id`` may be left out or must equal the path's."""

    model_config = ConfigDict(
        json_schema_extra={
            "description": "The RSU at the path's rsu_id. An id in the body that differs from the path's "
            "is refused (422, field 'id'): JSON Schema cannot compare a body field with the path.",
            "examples": [{"id": "S+000", "x": 0.0, "y": -3.875}],
        }
    )

    id: str | None = Field(
        None, pattern=RSU_ID_PATTERN, description="Optional; when given it must equal the rsu_id in the path."
    )


class RsuBulk(RequestModel):
    """Body of PUT /v1/rsus: RSUs to insert or replace, by id."""

    model_config = ConfigDict(
        json_schema_extra={
            "description": "RSUs to insert or replace, by id. Each id at most once per request: a repeated "
            "id is refused (422, field 'rsus[i].id'), which JSON Schema cannot state for objects.",
            "examples": [
                {
                    "rsus": [
                        {"id": "S+000", "x": 0.0, "y": -3.875},
                        {"id": "N+050", "x": 50.0, "y": 15.125, "range_std": 0.5},
                    ]
                }
            ],
        }
    )

    rsus: list[RsuModel] = Field(
        max_length=MAX_RSUS_PER_REQUEST, description="RSUs to upsert; ids must be unique within the request."
    )


class RsuOut(ResponseModel):
    """A roadside unit of the site's registry."""

    id: str = Field(description="RSU identifier.")
    x: float = Field(description=_X_DESCRIPTION)
    y: float = Field(description=_Y_DESCRIPTION)
    range_std: float | None = Field(description=_RANGE_STD)
    bearing_std: float | None = Field(description=_BEARING_STD)
    radius: float | None = Field(description=_RADIUS)


class RsuList(ResponseModel):
    rsus: list[RsuOut] = Field(description="Every registered RSU, sorted by id.")


class Upserted(ResponseModel):
    upserted: int = Field(description="How many RSUs were inserted or replaced.")


# -- broadcast ephemerides -------------------------------------------------------------------------
class GpsTimeOut(ResponseModel):
    """A GPS time three ways (GPS time has no leap seconds; BeiDou time = GPS time - 14 s)."""

    week: int = Field(description="GPS week number (continuous, not modulo 1024).")
    tow: float = Field(description="Seconds of that week, [0, 604800).")
    gps_seconds: float = Field(description="Seconds since the GPS epoch 1980-01-06 00:00:00 UTC.")


class EphemeridesOut(ResponseModel):
    """The site's loaded broadcast navigation file (RINEX 3), summarised."""

    digest: str = Field(
        description="SHA-256 (hex) of the file's text as stored (UTF-8, a leading byte-order mark dropped); "
        "every worker caches the parsed file by it."
    )
    size_bytes: int = Field(description="Size of the uploaded file (bytes).")
    uploaded_at: float = Field(description="Upload time (Unix seconds, server clock).")
    systems: list[str] = Field(
        description="Constellations with a healthy ephemeris (RINEX letters: G GPS, C BeiDou, E Galileo)."
    )
    satellite_count: int = Field(description="Satellites with at least one healthy ephemeris.")
    satellites: list[str] = Field(description="Those satellites, e.g. 'G05', 'C19', sorted.")
    records: dict[str, int] = Field(description="Keplerian ephemeris records read, by system letter.")
    healthy_records: int = Field(description="Of those, the healthy ones (the only ones used).")
    skipped_records: dict[str, int] = Field(
        description="Records of systems without a Keplerian ephemeris (R GLONASS, S SBAS), not used."
    )
    valid_from: GpsTimeOut | None = Field(
        description="Earliest time at which some healthy ephemeris is valid (its toe minus the fit "
        "interval or maximum age)."
    )
    valid_until: GpsTimeOut | None = Field(
        description="Latest time at which some healthy ephemeris is valid."
    )
    ionosphere: list[str] = Field(
        description="IONOSPHERIC CORR sets in the header (GPSA, GPSB: GPS Klobuchar; BDSA, BDSB; "
        "GAL: NeQuick)."
    )
    klobuchar: bool = Field(
        description="Whether the GPS Klobuchar coefficients (GPSA and GPSB) are present: the ionosphere "
        "correction the gnss_tight pipeline applies (options.ionosphere)."
    )


# -- pipelines -----------------------------------------------------------------------------------
class OptionOut(ResponseModel):
    """One option of a pipeline, with the value used when a session does not set it."""

    name: str = Field(description="Option name, as a key of the session's options object.")
    type: str = Field(
        description="JSON type: number, integer, boolean, string, string[], number[], "
        "matrix (list of rows) or object."
    )
    default: Any = Field(description="Value used when the option is not set (units as in the description).")
    description: str = Field(description="What the option does, with its unit.")
    minimum: float | None = Field(
        description="Smallest allowed value (numbers; of every element for number[] and matrix), else null."
    )
    maximum: float | None = Field(
        description="Largest allowed value (numbers; of every element for number[] and matrix), else null."
    )
    choices: list[Any] | None = Field(description="Allowed values (or list elements), else null.")


class PipelineOut(ResponseModel):
    name: str = Field(description="Pipeline name, used as 'pipeline' when creating a session.")
    description: str = Field(description="The method in one paragraph.")
    measurement_types: list[str] = Field(description="Measurement 'type' values this pipeline uses.")
    options: list[OptionOut] = Field(description="Every option with its default and bounds.")
    smoother: bool = Field(
        False, description="Whether GET /v1/sessions/{id}/track?smoothed=true is available for its sessions."
    )


class PipelineList(ResponseModel):
    pipelines: list[PipelineOut] = Field(description="Every pipeline offered by this server.")


# -- sessions ------------------------------------------------------------------------------------
class InitialStateIn(RequestModel):
    """A known starting point in the site frame; without it the pipeline initialises itself."""

    x: float = Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description="East position (m).")
    y: float = Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M, description="North position (m).")
    vx: float = Field(ge=-1000, le=1000, description="East velocity (m/s).")
    vy: float = Field(ge=-1000, le=1000, description="North velocity (m/s).")
    position_std: float = Field(
        1.0, ge=1.0e-3, le=1.0e4, description="1-sigma of each position component (m), 0.001-10000."
    )
    velocity_std: float = Field(
        1.0, ge=1.0e-3, le=1.0e3, description="1-sigma of each velocity component (m/s), 0.001-1000."
    )


class SessionCreate(RequestModel):
    """Body of POST /v1/sessions."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "vehicle_id": "bus-42",
                    "pipeline": "rsu_imu",
                    "options": {"range_std": 0.5},
                    "initial_state": {"x": 0.0, "y": 5.0, "vx": 10.0, "vy": 0.0},
                }
            ]
        }
    )

    vehicle_id: str = Field(
        pattern=VEHICLE_ID_PATTERN,
        description="The vehicle's own identifier: 1-128 characters of letters, digits, "
        "space and . _ : + @ / -.",
    )
    pipeline: str = Field(
        "rsu_imu", pattern=PIPELINE_NAME_PATTERN, description="Name of the pipeline (see GET /v1/pipelines)."
    )
    options: dict[str, Any] | None = Field(
        None,
        max_length=MAX_OPTIONS,
        description="Pipeline options by name (see GET /v1/pipelines); unset ones take their defaults. At "
        f"most {MAX_OPTIONS} (every pipeline has fewer, so a client may send all of a session's options back).",
    )
    initial_state: InitialStateIn | None = Field(
        None,
        description="Known initial position and velocity; null lets the pipeline initialise from RSU fixes. "
        "Its speed must not exceed the session's max_speed_mps option (else 422 naming initial_state.vx/vy).",
    )

    @field_validator("options")
    @classmethod
    def _finite(cls, value: dict[str, Any] | None) -> dict[str, Any] | None:
        _reject_non_finite(value, "options")
        return value


def _reject_non_finite(value: Any, path: str) -> None:
    """Raise if a JSON value holds NaN or infinity anywhere inside it."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{path} holds a non-finite number")
    if isinstance(value, dict):
        for key, item in value.items():
            _reject_non_finite(item, f"{path}.{key}")
    elif isinstance(value, list):
        for number, item in enumerate(value):
            _reject_non_finite(item, f"{path}[{number}]")


class SessionCreated(ResponseModel):
    """Answer to POST /v1/sessions: keep the token, it is shown only once."""

    session_id: str = Field(description="Identifier of the new session.")
    token: str = Field(
        description="Bearer token for this session's calls; shown once, stored only as a hash."
    )
    vehicle_id: str = Field(description="The vehicle identifier given.")
    pipeline: str = Field(description="Pipeline name.")
    options: dict[str, Any] = Field(description="Effective options: the given ones plus every default.")
    created_at: float = Field(description="Creation time (Unix seconds, server clock).")
    superseded: str | None = Field(
        None,
        description="The vehicle's previous live session, which this one replaced (its token now gets 409 "
        "superseded), or null when it had none. A vehicle has one live session at a time.",
    )


class SessionListItem(ResponseModel):
    """One live session as an operator's listing shows it."""

    session_id: str = Field(description="Session identifier.")
    vehicle_id: str = Field(description="The vehicle the session speaks for.")
    pipeline: str = Field(description="Pipeline name.")
    created_at: float = Field(description="Creation time (Unix seconds, server clock).")
    updated_at: float = Field(description="Time of the last applied batch, or of creation (Unix seconds).")
    last_seq: int = Field(description="seq of the last applied batch; 0 before any.")
    batches: int = Field(description="Batches applied.")
    epochs: int = Field(description="Epochs filtered (fixes produced).")
    last_fix_t: float | None = Field(
        None,
        description="t of the latest fix (the vehicle's measurement clock, s); null before the first fix.",
    )
    status: Literal["new", "initialised", "tracking", "predicted", "uninitialised", "diverged"] = Field(
        description="The latest fix's status, or 'new' before the first batch with a fix."
    )


class SessionList(ResponseModel):
    """A page of GET /v1/sessions, ordered by session id."""

    sessions: list[SessionListItem] = Field(description="Live sessions of this page.")
    next_after: str | None = Field(description="Pass as ?after= for the next page; null on the last page.")


# -- vehicle registry ------------------------------------------------------------------------------
class StateOut(ResponseModel):
    """The filter's full state estimate (combined over the model bank)."""

    components: list[str] = Field(
        description="Names of the components. rsu_imu: those estimated by every model of the bank, from: xp, "
        "xv, xa (east position m, velocity m/s, acceleration m/s^2), yp, yv, ya (north), "
        "phi (heading rad, CCW from east), "
        "omega (turn rate rad/s, CCW positive). gnss_tight: north, east, up (m: curvilinear offsets of "
        "latitude, longitude and height from the frame's origin), "
        "v_east, v_north, v_up (m/s), pitch, roll (rad), azimuth (rad, clockwise from north), clock_gps, "
        "clock_bds, clock_gal (receiver clock bias per constellation, m), clock_drift (m/s)."
    )
    mean: list[float] = Field(description="Mean, in the order of components (SI units as above).")
    covariance: list[list[float]] = Field(
        description="Covariance matrix, rows/columns in the order of components."
    )


class MeasurementUseOut(ResponseModel):
    index: int = Field(description="Index of the measurement in the request's measurements list (0-based).")
    type: str = Field(description="The measurement's type.")
    used: bool = Field(description="Whether it entered the filter update.")
    reason: str | None = Field(
        description="Why it was not used (out of range, failed the gate, ...), else null."
    )
    doppler_used: bool | None = Field(
        None,
        description="Only for a pseudorange sent with doppler_hz, else null: whether its Doppler (range rate) "
        "entered the update.",
    )
    doppler_reason: str | None = Field(
        None, description="Why the Doppler was not used, when doppler_used is false; else null."
    )
    correction_applied: bool | None = Field(
        None,
        description="Only for a pseudorange of a session with options.base_station, else null: whether the "
        "reference station's differential correction was added to it.",
    )
    correction_reason: str | None = Field(
        None,
        description="Why no correction was added, when correction_applied is false: 'no base data: ...', 'no "
        "correction for this satellite' (the base does not track it), 'correction too old: ...' (older than "
        "max_correction_age_s), 'ephemeris issue mismatch: ...' (base and rover used different IODE/toe), "
        "that its constellation is not among the session's correction_systems, or that the client sent the "
        "satellite's position; else null.",
    )
    noise_std: float | None = Field(
        None,
        description="gnss_tight, a pseudorange used in the update: its noise std there (m); else null.",
    )
    noise_reason: str | None = Field(
        None,
        description="gnss_tight, with noise_std: why the std is what it is: the noise model at the "
        "satellite's elevation (deg) and C/N0 (dB-Hz), the carrier smoothing factor, and, when its "
        "innovation against the filter's prediction is suspect, the down-weighting (options fault_*). "
        "An exclusion over time is in reason instead.",
    )


class FixOut(ResponseModel):
    """The estimate after one epoch (measurements sharing a timestamp), in the site frame."""

    t: float = Field(description="Epoch time (s, the vehicle's clock as sent).")
    status: Literal["initialised", "tracking", "predicted", "uninitialised", "diverged"] = Field(
        description="initialised: first fix; tracking: measurements were used; predicted: motion model only; "
        "uninitialised: nothing to start from yet (kinematic fields are null); diverged: the estimate broke a "
        "physical bound (the session's max_speed_mps, max_acceleration_mps2 or site_radius_m options), see "
        "divergence: do not use its position or velocity."
    )
    revised: bool = Field(
        False,
        description="true: this epoch was answered before and late measurements (the session's lag window, "
        "option max_delay_s) changed its estimate; this fix replaces the earlier one of the same t. A client "
        "keeps the last fix it received for each t.",
    )
    divergence: str | None = Field(
        None,
        description="Only with status diverged, else null: which bound the estimate broke, by how much (m, m/s, "
        "m/s^2, s), and what the server did. With the session option on_divergence=reset (the default) the "
        "session was reset: the following fixes are uninitialised until the pipeline starts again from its "
        "next measurements, and the client should keep sending them (an initial_state needs a new session). "
        "With on_divergence=report the filter went on from this estimate: treat the following fixes with "
        "suspicion, or open a new session.",
    )
    x: float | None = Field(
        description="East position (m) in the site frame (gnss_tight: the tangent plane at the configured "
        "WGS-84 origin, or without one at the session's first fix)."
    )
    y: float | None = Field(description="North position (m), same frame as x.")
    vx: float | None = Field(description="East velocity (m/s).")
    vy: float | None = Field(description="North velocity (m/s).")
    speed: float | None = Field(description="Speed over ground (m/s).")
    heading: float | None = Field(description="Course over ground (rad, CCW from east, in [-pi, pi]).")
    yaw_rate: float | None = Field(description="Turn rate (rad/s, CCW positive).")
    latitude: float | None = Field(
        description="WGS-84 latitude (rad): the estimate itself for pipelines that estimate a global "
        "position (gnss_tight), else (x, y) on the site's tangent plane; null when neither applies (no "
        "WGS-84 origin configured)."
    )
    longitude: float | None = Field(
        description="WGS-84 longitude (rad, east positive), as latitude; null when latitude is."
    )
    height: float | None = Field(
        None,
        description="WGS-84 ellipsoidal height (m) of pipelines that estimate it (gnss_tight); else null.",
    )
    position_covariance: list[list[float]] | None = Field(
        description="2x2 covariance of (x, y) (m^2), [[xx, xy], [yx, yy]]."
    )
    state: StateOut | None = Field(
        description="Full state estimate; only when the batch asked include_state."
    )
    model_probabilities: dict[str, float] = Field(description="Probability of each motion model of the bank.")
    nis: float | None = Field(
        description="Normalised innovation squared of the epoch's update (dimensionless); "
        "null without an update."
    )
    nis_dof: int = Field(description="Degrees of freedom of nis (the measurement dimension used).")
    constraints: list[str] | None = Field(
        None,
        description="gnss_tight: the vehicle pseudo-measurements in this epoch's update when the batch had no "
        "riss sample: 'non-holonomic' (zero lateral and vertical velocity in the vehicle frame, options nhc*), "
        "'zero-velocity' (the Doppler speed stayed below zupt_speed_mps for zupt_epochs epochs, options "
        "zupt*); an empty list when none. null for other pipelines.",
    )
    protection_level_m: float | None = Field(
        None,
        description="Horizontal protection level (m, site frame x/y): the horizontal position error exceeds it, "
        "while integrity is not alarm, with at most the session's integrity_risk per epoch, even when one RSU is "
        "faulty, however slowly its fault grew (rsu_imu: filter-based solution separation, one sub-filter per "
        "RSU left out, docs/integrity.md; gnss_tight: solution separation of one-satellite and one-constellation "
        "faults with the filter's prediction as prior, from the fix's covariance (the filter's, with "
        "error_correlation's factor for time-correlated errors) times integrity_inflation, "
        "docs/integrity.md GNSS; v2v_coop and v2x_federated: solution separation of the fix's GNSS fix and each "
        "neighbour or RSU ranged to, at the epoch). Null when integrity is unavailable.",
    )
    integrity: Literal["ok", "alarm", "unavailable"] = Field(
        "unavailable",
        description="ok: protection_level_m is within the session's alert_limit_m and every fault test passed or "
        "its RSU or neighbour was excluded; "
        "alarm: do not use this fix for what needs integrity (the protection level exceeds the alert limit, a "
        "fault was detected that could not be excluded, or the fix diverged); unavailable: no bound for this "
        "fix (the first epochs of a session, a session without the monitor, or a pipeline without one: "
        "rsu_imu and gnss_tight run theirs unless the session's options.integrity is false, v2v_coop and "
        "v2x_federated only when it is true; gnss_tight is also unavailable in an epoch with fewer than "
        "4 + constellations satellites, too few to bound a fault; the v2v_coop method gps, whose fix nothing "
        "checks, always).",
    )
    measurements: list[MeasurementUseOut] = Field(
        description="The batch's measurements of this epoch: used or why not (a revised fix lists only the "
        "late measurements this batch brought to its epoch). Measurements older than the lag window are "
        "listed in the batch's newest fix, used false, with how late they were."
    )


class BatchOut(ResponseModel):
    """Answer to a batch: one fix per epoch, in time order."""

    seq: int = Field(description="The batch's seq.")
    fixes: list[FixOut] = Field(
        description="One fix per epoch of the batch and, when late measurements arrived, a revised fix for "
        "each earlier epoch they changed (revised true), all in time order."
    )


class FixEventOut(ResponseModel):
    """The data of one ``fix`` event of the fix stream (GET /v1/stream/fixes): one fix of an applied batch."""

    session_id: str = Field(description="The session whose batch produced the fix.")
    vehicle_id: str = Field(description="The session's vehicle.")
    pipeline: str = Field(description="The session's pipeline.")
    seq: int = Field(description="The seq of the batch that produced the fix.")
    fix: FixOut = Field(
        description="The fix exactly as the batch's answer carried it, except state, which is always null on the "
        "stream (read the session's track for the state covariance)."
    )


class StreamMissedOut(ResponseModel):
    """The data of a ``missed`` event: sent first when a consumer resumes from an id whose successors the
    stream's buffer (EDGEPOS_STREAM_BUFFER) no longer holds, or when this worker's reader fell behind it;
    the stream then goes on with the oldest fixes it holds."""

    reason: Literal["trimmed", "unknown"] = Field(
        description="trimmed: the fixes after last_event_id were older than the buffer holds (missed says how "
        "many); unknown: last_event_id is ahead of the stream (its buffer was reset, e.g. the in-process store "
        "restarted), so how many were missed is not known."
    )
    last_event_id: str | None = Field(
        description="The id the consumer resumed from (null: the worker fell behind)."
    )
    missed: int | None = Field(description="How many fixes were missed, when known.")
    oldest_event_id: str | None = Field(description="The oldest id the buffer holds now (null: it is empty).")
    message: str = Field(description="The same in words.")


class StreamEndOut(ResponseModel):
    """The data of an ``end`` event: the last event of a stream that the server ends."""

    reason: Literal["slow_consumer", "session_ended"] = Field(
        description="slow_consumer: the consumer fell EDGEPOS_STREAM_QUEUE fixes behind and was dropped so that it "
        "holds nobody back (reconnect with Last-Event-ID to resume); session_ended: the session whose token "
        "opened the stream was deleted, superseded or expired."
    )
    last_event_id: str | None = Field(description="The id of the last fix sent on this stream (null: none).")
    message: str = Field(description="The same in words.")


class TrackOut(ResponseModel):
    """The estimates of a session's lag window, one per epoch, oldest first."""

    session_id: str = Field(description="Session identifier.")
    pipeline: str = Field(description="Pipeline name.")
    smoothed: bool = Field(
        description="false: filtered estimates (each from the data up to its t); true: fixed-interval "
        "smoothed over the window (Rauch-Tung-Striebel; an IMM smoother for rsu_imu): each from every "
        "measurement in the window, so the oldest epochs gain the most."
    )
    max_delay_s: float = Field(description="The session's lag window (s).")
    start_t: float | None = Field(
        description="The window's oldest epoch (s, vehicle clock), null when empty."
    )
    end_t: float | None = Field(description="The session's newest epoch (s), null before any.")
    fixes: list[FixOut] = Field(
        description="One estimate per epoch of the window, in time order (measurements lists are empty)."
    )


class SessionOut(ResponseModel):
    """A session's configuration, counters and latest estimate."""

    session_id: str = Field(description="Session identifier.")
    vehicle_id: str = Field(description="The vehicle identifier given at creation.")
    pipeline: str = Field(description="Pipeline name.")
    options: dict[str, Any] = Field(description="Effective options.")
    last_seq: int = Field(description="seq of the last applied batch; 0 before any.")
    batches: int = Field(description="Batches applied.")
    epochs: int = Field(description="Epochs filtered (fixes produced).")
    initialised: bool = Field(description="Whether the filter has a position estimate yet.")
    t: float | None = Field(
        description="Time of the last epoch processed (s, vehicle clock), null before any."
    )
    model_probabilities: dict[str, float] = Field(description="Current probability of each motion model.")
    last_fix: FixOut | None = Field(
        description="The latest fix (without the full state), null before any batch."
    )
    created_at: float = Field(description="Creation time (Unix seconds, server clock).")
    updated_at: float = Field(
        description="Time of the last applied batch or creation (Unix seconds, server clock)."
    )


# -- health --------------------------------------------------------------------------------------
class Health(ResponseModel):
    status: Literal["ok"] = Field(description="Always 'ok' while the process serves requests.")


class Ready(ResponseModel):
    status: Literal["ready"] = Field(description="'ready' when the store answers.")
