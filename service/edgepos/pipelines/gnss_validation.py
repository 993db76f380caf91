"""The gnss_tight pipeline's checks of a batch's observations, before any of them touches the session.

The API's schemas check the wire; these check the observations themselves (a client of the pipeline
package, such as ``edgepos eval``, builds them without the API) and name every bad field at once, so a
batch is refused whole and the session stays as it was.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from edgepos.core.observations import Observation, PseudorangeObservation, RissObservation
from edgepos.pipelines.base import PipelineInputError, Problem, is_finite_number
from edgepos.pipelines.gnss_options import (
    MAX_CARRIER_CYCLES,
    MAX_DOPPLER_HZ,
    MAX_LLI,
    MAX_PRN,
    SECONDS_PER_WEEK,
    SYSTEMS,
)

SAT_RADIUS_M = (1.0e7, 5.0e7)
"""Geocentric distances a client-sent satellite position must lie between (MEO to GEO/IGSO)."""
MAX_SAT_SPEED_MPS = 1.0e4
"""Bound on each component of a client-sent satellite velocity (m/s): Earth-fixed velocities of MEO
satellites are about 3-4 km/s, of GEO/IGSO up to about 3 km/s."""
MAX_SAT_CLOCK_DRIFT = 1.0e-6
"""Bound on a client-sent satellite clock drift (s/s): broadcast drifts are below 1e-9."""
_RISS_BOUNDS = (("wheel_speed", 100.0), ("accel_x", 50.0), ("accel_y", 50.0), ("gyro_z", 10.0))


def validate_batch(session_t: float | None, observations: Sequence[Observation]) -> None:
    """PipelineInputError naming every field of ``observations`` the pipeline cannot take: times outside the
    week or before the session's last epoch (``session_t``), values out of range, types it does not use."""
    problems: list[Problem] = []
    for index, observation in enumerate(observations):
        if not is_finite_number(observation.t) or not 0.0 <= observation.t < SECONDS_PER_WEEK:
            problems.append(Problem(index, "t", "must be a GPS time of week in [0, 604800) s"))
        elif session_t is not None and observation.t < session_t:
            problems.append(
                Problem(
                    index, "t", f"{observation.t!r} is older than the session's last epoch t={session_t!r}"
                )
            )
        if isinstance(observation, PseudorangeObservation):
            problems.extend(_pseudorange_problems(index, observation))
        elif isinstance(observation, RissObservation):
            for name, bound in _RISS_BOUNDS:
                value = getattr(observation, name)
                if not is_finite_number(value) or abs(value) > bound:
                    problems.append(Problem(index, name, f"must be finite and within +-{bound:g}"))
        else:
            problems.append(
                Problem(index, "type", f"{observation.kind!r} is not used by the gnss_tight pipeline")
            )
    if problems:
        raise PipelineInputError(problems)


def _pseudorange_problems(index: int, observation: PseudorangeObservation) -> list[Problem]:
    problems: list[Problem] = []
    if observation.system not in SYSTEMS:
        problems.append(Problem(index, "system", f"must be one of {list(SYSTEMS)}"))
    if not isinstance(observation.prn, int) or not 1 <= observation.prn <= MAX_PRN:
        problems.append(Problem(index, "prn", f"must be an integer in [1, {MAX_PRN}]"))
    if not is_finite_number(observation.pseudorange) or not 1.0e6 <= observation.pseudorange <= 1.0e8:
        problems.append(Problem(index, "pseudorange", "must be a finite range in [1e6, 1e8] m"))
    if not is_finite_number(observation.cn0) or not 0.0 <= observation.cn0 <= 100.0:
        problems.append(Problem(index, "cn0", "must be a finite C/N0 in [0, 100] dB-Hz"))
    if observation.sat_position is not None:
        position = observation.sat_position
        if len(position) != 3 or not all(is_finite_number(v) for v in position):
            problems.append(Problem(index, "sat_position", "must be three finite ECEF coordinates (m)"))
        elif not SAT_RADIUS_M[0] <= math.hypot(*position) <= SAT_RADIUS_M[1]:
            problems.append(Problem(index, "sat_position", "must lie 1e7..5e7 m from the Earth's centre"))
    if observation.sat_clock is not None and (
        not is_finite_number(observation.sat_clock) or abs(observation.sat_clock) > 0.01
    ):
        problems.append(Problem(index, "sat_clock", "must be a finite offset within +-0.01 s"))
    problems.extend(_rate_problems(index, observation))
    if observation.doppler_hz is not None and (
        not is_finite_number(observation.doppler_hz) or abs(observation.doppler_hz) > MAX_DOPPLER_HZ
    ):
        problems.append(
            Problem(index, "doppler_hz", f"must be a finite Doppler within +-{MAX_DOPPLER_HZ:g} Hz")
        )
    if observation.carrier_cycles is not None and (
        not is_finite_number(observation.carrier_cycles)
        or abs(observation.carrier_cycles) >= MAX_CARRIER_CYCLES
    ):
        problems.append(
            Problem(index, "carrier_cycles", f"must be a finite phase within +-{MAX_CARRIER_CYCLES:g} cycles")
        )
    if observation.lli is not None and (
        isinstance(observation.lli, bool)
        or not isinstance(observation.lli, int)
        or not 0 <= observation.lli <= MAX_LLI
    ):
        problems.append(
            Problem(index, "lli", f"must be an integer in [0, {MAX_LLI}] (RINEX loss-of-lock bits)")
        )
    return problems


def _rate_problems(index: int, observation: PseudorangeObservation) -> list[Problem]:
    """A client's satellite velocity and clock drift: finite, bounded, and sent together with each other
    and with the satellite's position and clock (the range-rate model needs all four)."""
    problems: list[Problem] = []
    velocity, drift = observation.sat_velocity, observation.sat_clock_drift
    if velocity is not None:
        if len(velocity) != 3 or not all(is_finite_number(v) for v in velocity):
            problems.append(Problem(index, "sat_velocity", "must be three finite ECEF velocities (m/s)"))
        elif not all(abs(v) <= MAX_SAT_SPEED_MPS for v in velocity):
            problems.append(
                Problem(index, "sat_velocity", f"each component must lie within +-{MAX_SAT_SPEED_MPS:g} m/s")
            )
    if drift is not None and (not is_finite_number(drift) or abs(drift) > MAX_SAT_CLOCK_DRIFT):
        problems.append(
            Problem(index, "sat_clock_drift", f"must be a finite drift within +-{MAX_SAT_CLOCK_DRIFT:g} s/s")
        )
    if (velocity is None) != (drift is None):
        missing = "sat_clock_drift" if velocity is not None else "sat_velocity"
        problems.append(
            Problem(index, missing, "sat_velocity and sat_clock_drift go together: send both or neither")
        )
    elif velocity is not None and (observation.sat_position is None or observation.sat_clock is None):
        problems.append(
            Problem(
                index, "sat_velocity", "goes with sat_position and sat_clock: send them too, or leave it out"
            )
        )
    return problems
