"""Plain-data observations as the estimation core receives them (already validated, SI units).

Times are seconds on the session's clock; angles are radians. Each type names itself with ``kind``,
the same word the wire protocol uses as its discriminator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar


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


Observation = RsuObservation | GyroObservation
