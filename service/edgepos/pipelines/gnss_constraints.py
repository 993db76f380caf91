"""Vehicle constraints without RISS (issue 16, item 5): pseudo-measurements ``gnss_tight`` adds to an epoch's
update when no ``riss`` sample came in the batch (the RISS model already moves along its azimuth).

* Non-holonomic constraint (``nhc``): a road vehicle does not slide sideways or move vertically in its own
  frame. With the GNSS-only model the heading is the azimuth psi of the predicted velocity (fixed for the
  update: it is the vehicle's heading at the start of the interval), so the rows are the lateral velocity
  v_e cos psi - v_n sin psi = 0 with std ``nhc_lateral_accel_std`` x dt (the heading turns during the
  interval: the lateral acceleration of a car in town, relative to where it was heading) and the vertical
  velocity v_u = 0 with std ``nhc_vertical_std_mps`` (road grades). Applied only above
  ``NHC_MIN_SPEED_MPS``: at rest the heading is undefined.
* Zero-velocity update (``zupt``): when the epoch's own Doppler velocity (least squares at the predicted
  position, ``spp.solve_velocity``, independent of the filter) has been below ``zupt_speed_mps`` for
  ``zupt_epochs`` consecutive epochs, v_e = v_n = v_u = 0 with std ``zupt_std_mps``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edgepos.core.motion import riss as layout
from edgepos.core.particles import Measurement
from edgepos.gnss.measurements import PseudorangeSet
from edgepos.gnss.spp import SppError, solve_velocity
from edgepos.pipelines.gnss_session import GnssSession

NHC_MIN_SPEED_MPS = 1.0
"""Below this predicted speed the heading, and so the non-holonomic frame, is not defined."""
_MIN_STD = 0.01


@dataclass(frozen=True)
class Constraint:
    """Pseudo-measurement rows: z = 0 for h(states) = states @ rows.T, with their variances and a name for
    the fix's report."""

    name: str
    rows: np.ndarray
    variances: np.ndarray

    def predict(self, states: np.ndarray) -> np.ndarray:
        value: np.ndarray = states @ self.rows.T
        return value


def non_holonomic(
    centre: np.ndarray, dt: float, lateral_accel_std: float, vertical_std: float
) -> Constraint | None:
    """The NHC rows at the predicted state ``centre``; None when it moves slower than NHC_MIN_SPEED_MPS."""
    ve, vn = float(centre[layout.VE]), float(centre[layout.VN])
    speed = math.hypot(ve, vn)
    if speed < NHC_MIN_SPEED_MPS:
        return None
    sin_psi, cos_psi = ve / speed, vn / speed
    rows = np.zeros((2, layout.DIM))
    rows[0, layout.VE] = cos_psi
    rows[0, layout.VN] = -sin_psi
    rows[1, layout.VU] = 1.0
    lateral = max(lateral_accel_std * max(dt, 0.0), _MIN_STD)
    return Constraint("non-holonomic", rows, np.array([lateral**2, max(vertical_std, _MIN_STD) ** 2]))


def zero_velocity(std: float) -> Constraint:
    """The ZUPT rows: east, north and up velocity zero."""
    rows = np.zeros((3, layout.DIM))
    rows[0, layout.VE] = rows[1, layout.VN] = rows[2, layout.VU] = 1.0
    return Constraint("zero-velocity", rows, np.full(3, max(std, _MIN_STD) ** 2))


def doppler_speed(
    prs: PseudorangeSet, receiver_ecef: np.ndarray, elevation: np.ndarray, rate_rows: np.ndarray
) -> float | None:
    """Horizontal speed (m/s) of this epoch's own Doppler least-squares velocity at ``receiver_ecef`` from
    the rows that passed the range-rate tests; None when it cannot be solved (too few, a failed test)."""
    if rate_rows.size < 5:
        return None
    usable = np.zeros(len(prs), dtype=bool)
    usable[rate_rows] = True
    try:
        solution = solve_velocity(prs, receiver_ecef, elevation, usable)
    except SppError:
        return None
    if not solution.chi2_passed:
        return None
    return float(math.hypot(solution.velocity_enu[0], solution.velocity_enu[1]))


def epoch_constraints(
    session: GnssSession,
    centre: np.ndarray,
    dt: float,
    prs: PseudorangeSet,
    receiver: np.ndarray,
    elevation: np.ndarray,
    rate_rows: np.ndarray,
) -> list[Constraint]:
    """The vehicle constraints of an epoch without RISS input: zero velocity when the Doppler speed has
    stayed low for ``zupt_epochs`` (counted here), else the non-holonomic constraint while moving. Sessions
    stored before the options existed have neither."""
    options = session.options
    if options.get("zupt", False):
        # Solved only when the prediction is near rest: a car the filter sees moving faster than the
        # heading threshold does not stand still within one epoch (the count starts at the next).
        slow = math.hypot(centre[layout.VE], centre[layout.VN]) < NHC_MIN_SPEED_MPS
        speed = doppler_speed(prs, receiver, elevation, rate_rows) if slow else None
        still = speed is not None and speed < options["zupt_speed_mps"]
        session.still_epochs = session.still_epochs + 1 if still else 0
        if session.still_epochs >= options["zupt_epochs"]:
            return [zero_velocity(options["zupt_std_mps"])]
    if options.get("nhc", False):
        constraint = non_holonomic(
            centre, dt, options["nhc_lateral_accel_std"], options["nhc_vertical_std_mps"]
        )
        if constraint is not None:
            return [constraint]
    return []


def with_constraints(measurement: Measurement, constraints: list[Constraint]) -> Measurement:
    """The epoch's measurement with the constraints' zero-valued rows appended (their outlier variance is
    their own: no heavy tail for a pseudo-measurement)."""
    if not constraints:
        return measurement
    extra_var = np.concatenate([c.variances for c in constraints])
    base_predict = measurement.predict

    def predict(states: np.ndarray) -> np.ndarray:
        return np.concatenate([base_predict(states)] + [c.predict(states) for c in constraints], axis=-1)

    outlier_variance: float | np.ndarray = measurement.outlier_variance
    if measurement.outlier_probability > 0.0:
        outlier_variance = np.concatenate(
            [np.broadcast_to(measurement.outlier_variance, measurement.z.shape), extra_var]
        )
    return Measurement(
        predict,
        np.concatenate([measurement.z, np.zeros(extra_var.size)]),
        np.concatenate([measurement.variances, extra_var]),
        measurement.outlier_probability,
        outlier_variance,
    )
