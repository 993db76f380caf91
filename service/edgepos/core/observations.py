"""Plain-data observations as the estimation core receives them (already validated, SI units).

Times are seconds on the session's clock; angles are radians. Each type names itself with ``kind``,
the same word the wire protocol uses as its discriminator. A new field goes last and is optional: the
lag window's stored records (``core.observation_codec``) follow the field order, and older layouts are
read through ``LEGACY_LAYOUTS``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, cast

SPEED_OF_LIGHT = 299_792_458.0
"""m/s, exact (SI); converts a one-way time of arrival to metres."""


@dataclass(frozen=True, slots=True)
class RsuObservation:
    """Range (m) and bearing (rad, from the RSU to the vehicle, CCW from +x) measured by one RSU."""

    kind: ClassVar[str] = "rsu"
    t: float
    rsu_id: str
    range: float
    bearing: float


@dataclass(frozen=True, slots=True)
class GyroObservation:
    """Yaw rate (rad/s, counter-clockwise positive) from the vehicle's gyro."""

    kind: ClassVar[str] = "gyro"
    t: float
    yaw_rate: float


@dataclass(frozen=True, slots=True)
class RsuRangeObservation:
    """Range only (m) from a known ranging node (an RSU) to the vehicle."""

    kind: ClassVar[str] = "rsu_range"
    t: float
    rsu_id: str
    range: float


@dataclass(frozen=True, slots=True)
class GnssFixObservation:
    """A GNSS receiver's position solution (m, site frame), with its 1-sigma per axis when known."""

    kind: ClassVar[str] = "gnss_fix"
    t: float
    x: float
    y: float
    std: float | None = None


@dataclass(frozen=True, slots=True)
class OdometerObservation:
    """Wheel odometry: distance travelled (m) since the previous odometer reading, or speed (m/s).

    Exactly one of ``distance`` and ``speed`` is set."""

    kind: ClassVar[str] = "odometer"
    t: float
    distance: float | None = None
    speed: float | None = None


@dataclass(frozen=True, slots=True)
class V2vRangeObservation:
    """Range to a neighbour vehicle: metres, or one-way time of arrival (s) to be scaled by c.

    Exactly one of ``range`` and ``toa`` is set; ``peer_vehicle_id`` names the neighbour's session."""

    kind: ClassVar[str] = "v2v_range"
    t: float
    peer_vehicle_id: str
    range: float | None = None
    toa: float | None = None

    @property
    def metres(self) -> float:
        """The range in metres: ``range``, or ``toa`` times the speed of light in vacuum."""
        # toa is set when range is not: the API's schema accepts exactly one of the two.
        return self.range if self.range is not None else float(cast(float, self.toa)) * SPEED_OF_LIGHT


@dataclass(frozen=True, slots=True)
class PseudorangeObservation:
    """One satellite's code pseudorange (m) and carrier-to-noise density (dB-Hz).

    ``t`` is the receive time as GPS time of week (s). ``system`` is the RINEX letter ("G" GPS,
    "C" BeiDou, "E" Galileo). When the client has computed the satellite's state itself,
    ``sat_position`` is its ECEF (WGS-84) position in metres at transmit time, expressed in the
    ECEF frame of the transmit epoch (the receiver applies the Earth-rotation correction), and
    ``sat_clock`` its clock offset in seconds (corrected range = pseudorange + c * sat_clock);
    otherwise the service computes both from the broadcast ephemerides. ``doppler_hz`` is the receiver's
    Doppler of the same signal (Hz, RINEX sign: positive when the satellite approaches, so the range rate
    is -doppler_hz times the carrier's wavelength), None when not sent. ``carrier_cycles`` is the
    receiver's carrier phase of the same signal (cycles, RINEX convention: it grows with the range, so it
    changes by -doppler_hz per second) and ``lli`` its RINEX loss-of-lock indicator bits (bit 0: lock lost
    since the previous epoch, so the phase may have slipped), None when not sent. With ``sat_position`` and
    ``sat_clock`` a client may also send the satellite's ECEF velocity (m/s, the derivative of
    ``sat_position``'s Earth-fixed coordinates) as ``sat_velocity`` and its clock drift (s/s) as
    ``sat_clock_drift``: what the range-rate model needs of a satellite to use a Doppler."""

    kind: ClassVar[str] = "pseudorange"
    t: float
    system: str
    prn: int
    pseudorange: float
    cn0: float
    sat_position: tuple[float, float, float] | None = None
    sat_clock: float | None = None
    doppler_hz: float | None = None
    carrier_cycles: float | None = None
    lli: int | None = None
    sat_velocity: tuple[float, float, float] | None = None
    sat_clock_drift: float | None = None


@dataclass(frozen=True, slots=True)
class RissObservation:
    """Reduced inertial sensor system sample: wheel speed (m/s), forward and lateral specific force
    (m/s^2, vehicle frame: x forward, y left) and yaw rate (rad/s, counter-clockwise positive)."""

    kind: ClassVar[str] = "riss"
    t: float
    wheel_speed: float
    accel_x: float
    accel_y: float
    gyro_z: float


@dataclass(frozen=True, slots=True)
class PseudorangeObservationV2:
    """The pseudorange observation as lag windows of version 2 stored it (before ``doppler_hz``): read
    only, to convert such records (``pipelines.lag_state``)."""

    kind: ClassVar[str] = "pseudorange"
    t: float
    system: str
    prn: int
    pseudorange: float
    cn0: float
    sat_position: tuple[float, float, float] | None = None
    sat_clock: float | None = None

    def current(self) -> PseudorangeObservation:
        """The same observation in today's form (no Doppler)."""
        return PseudorangeObservation(
            self.t, self.system, self.prn, self.pseudorange, self.cn0, self.sat_position, self.sat_clock
        )


@dataclass(frozen=True, slots=True)
class PseudorangeObservationV3:
    """The pseudorange observation's fields before ``carrier_cycles`` and ``lli``: the layout the lag window
    (version 3) stores pseudoranges without carrier phase in, so windows stored before carrier phase existed
    read unchanged (``core.observation_codec``)."""

    kind: ClassVar[str] = "pseudorange"
    t: float
    system: str
    prn: int
    pseudorange: float
    cn0: float
    sat_position: tuple[float, float, float] | None = None
    sat_clock: float | None = None
    doppler_hz: float | None = None


@dataclass(frozen=True, slots=True)
class PseudorangeObservationV4:
    """The pseudorange observation's fields before ``sat_velocity`` and ``sat_clock_drift``: the layout the
    lag window stores pseudoranges with carrier phase and without a client's satellite velocity in, so
    windows stored before those fields existed read unchanged (``core.observation_codec``)."""

    kind: ClassVar[str] = "pseudorange"
    t: float
    system: str
    prn: int
    pseudorange: float
    cn0: float
    sat_position: tuple[float, float, float] | None = None
    sat_clock: float | None = None
    doppler_hz: float | None = None
    carrier_cycles: float | None = None
    lli: int | None = None


Observation = (
    RsuObservation
    | GyroObservation
    | RsuRangeObservation
    | GnssFixObservation
    | OdometerObservation
    | V2vRangeObservation
    | PseudorangeObservation
    | RissObservation
)
