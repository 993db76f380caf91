"""Pipeline ``v2v_coop``: GPS, dead reckoning and V2V time-of-arrival ranging (Qiao & Qu 2021).

State [xp, xv, xa, yp, yv, ya] in the site frame, predicted with nearly constant acceleration
(the paper's DR model, eq. 2: acceleration noise ``accel_std`` per step). Option ``method``:

* ``gps``: the receiver's fixes as they are (position = fix; velocity from consecutive fixes);
* ``gps_dr``: Kalman filter on the fixes, with the gyro yaw rate and odometer distance as
  (linearised) dead-reckoning measurements;
* ``ukf``: the same plus V2V ranges in a UKF that takes each neighbour's estimate as its exact
  position (the paper's "traditional UKF", sec. 3.1);
* ``aug_ukf``: the improved UKF (sec. 3.2, eqs. 8-26): the neighbours' positions and covariances
  are appended to the state for the range update (``core.augmented``).

A neighbour's position at the range's time is read from its own session's published track
(``pipelines.tracks.position_at``); a neighbour without one, stale, or the vehicle itself is
skipped and the fix says why.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from edgepos.core import gnss_bias
from edgepos.core import state as state_format
from edgepos.core.augmented import augmented_update
from edgepos.core.consistency import ConsistencyScale, scaled_position
from edgepos.core.cooperative_integrity import RangeSource
from edgepos.core.filters.ekf import ExtendedKalmanFilter
from edgepos.core.filters.ukf import UnscentedKalmanFilter
from edgepos.core.gnss_bias import Bias
from edgepos.core.integrity import ALARM, UNAVAILABLE, Protection
from edgepos.core.intersection import range_weight
from edgepos.core.measurements.gnss_fix import GnssPosition
from edgepos.core.measurements.rsu import RsuRange
from edgepos.core.motion.ca import ConstantAcceleration
from edgepos.core.numerics import FloatArray
from edgepos.core.observations import (
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    V2vRangeObservation,
)
from edgepos.pipelines.base import (
    Environment,
    Fix,
    InitialState,
    MeasurementUse,
    OptionSpec,
    Pipeline,
    StateSummary,
    ensure_finite_fixes,
)
from edgepos.pipelines.cooperative_consistency import factor, observe, protection_scale
from edgepos.pipelines.cooperative_integrity import (
    COOPERATIVE_INTEGRITY_SPECS,
    LEGACY_INTEGRITY,
    fix_source,
    monitor,
    screen_neighbours,
    with_protection,
)
from edgepos.pipelines.cooperative_options import (
    GNSS_BIAS_SPECS,
    LEGACY_CONSISTENCY,
    LEGACY_OPTIONS,
    consistency_specs,
    neighbour_specs,
)
from edgepos.pipelines.epochs import group_by_time
from edgepos.pipelines.kinematic import (
    KINEMATIC,
    check_batch,
    dead_reckoning_update,
    heading_known,
    kinematic_fix,
    shared_point,
    wait_for_heading,
)
from edgepos.pipelines.options import resolve_options
from edgepos.pipelines.tracks import NeighbourUnavailable, position_at

METHODS = ("gps", "gps_dr", "ukf", "aug_ukf")
_INITIAL_VELOCITY_STD = 30.0
_INITIAL_ACCEL_STD = 1.0
CONSISTENCY_DEFAULT = False

OPTION_SPECS = (
    OptionSpec(
        "method",
        "string",
        "aug_ukf",
        "gps (fixes as they are), gps_dr (Kalman filter with dead reckoning), ukf (plus V2V ranges, "
        "neighbours' estimates taken as exact) or aug_ukf (neighbours' positions augmented into the state).",
        choices=METHODS,
    ),
    OptionSpec(
        "gps_std",
        "number",
        5.0 / math.sqrt(2.0),
        "GNSS fix total error 1-sigma per axis (m) when a fix carries none; gnss_bias_std of it is the "
        "time-correlated part, the rest white.",
        minimum=1e-3,
        maximum=1e4,
    ),
    *GNSS_BIAS_SPECS,
    OptionSpec(
        "accel_std",
        "number",
        0.3,
        "Acceleration change 1-sigma per step (m/s^2), the DR model's noise.",
        minimum=1e-4,
        maximum=100.0,
    ),
    OptionSpec("gyro_std", "number", 0.005, "Gyro yaw-rate 1-sigma (rad/s).", minimum=1e-6, maximum=10.0),
    OptionSpec(
        "odometer_std",
        "number",
        0.1,
        "Odometer distance 1-sigma per reading (m); for speed readings (m/s).",
        minimum=1e-6,
        maximum=1e3,
    ),
    OptionSpec(
        "range_std",
        "number",
        2.0,
        "V2V range 1-sigma (m); a TOA's 1-sigma times c.",
        minimum=1e-3,
        maximum=1e4,
    ),
    *neighbour_specs(
        "How a neighbour's estimate enters a range update: intersection (covariance intersection with this "
        "vehicle's own estimate: consistent whatever their correlation, e.g. GNSS errors they share) or "
        "independent (as independent information, the paper's; over-confident when they share errors)."
    ),
    *COOPERATIVE_INTEGRITY_SPECS,
    *consistency_specs(
        CONSISTENCY_DEFAULT,
        "the fix filter's; not for method gps, whose fix is the receiver's with the receiver's std",
    ),
)

_KF = ExtendedKalmanFilter()  # exact for the linear motion and fixes; linearises the DR measurements
# kappa = 0: the centre point's weight stays non-negative for the augmented dimensions (6 + 2N).
_UKF = UnscentedKalmanFilter(alpha=1.0, beta=2.0, kappa=0.0)


@dataclass
class _SessionState:
    options: dict[str, Any]
    initialised: bool
    t: float | None
    epochs: int
    odometer_t: float | None  # time of the last odometer distance reading (start of the next interval)
    mean: np.ndarray  # (6,) the fix: every measurement this method uses
    cov: np.ndarray  # (6, 6)
    own_mean: np.ndarray  # (6,) GNSS + dead reckoning only: what the vehicle shares with its neighbours
    own_cov: np.ndarray  # (6, 6)
    bias: Bias  # the GNSS fix error's Gauss-Markov part beside mean/cov
    own_bias: Bias  # and beside own_mean/own_cov
    held: dict[str, float] = dataclasses.field(default_factory=dict)  # neighbours held out: id -> until t
    seen: dict[str, float] = dataclasses.field(default_factory=dict)  # neighbours' last track point tested
    consistency: ConsistencyScale = dataclasses.field(
        default_factory=ConsistencyScale
    )  # the fix filter's, from its GNSS fix innovations

    def to_bytes(self) -> bytes:
        meta = {
            "pipeline": V2vCoopPipeline.name,
            "options": self.options,
            "initialised": self.initialised,
            "t": self.t,
            "epochs": self.epochs,
            "odometer_t": self.odometer_t,
            "held": self.held,
            "seen": self.seen,
            "consistency": self.consistency.to_list(),
        }
        arrays = {
            "mean": self.mean,
            "cov": self.cov,
            "own_mean": self.own_mean,
            "own_cov": self.own_cov,
            "bias": self.bias.arrays(),
            "own_bias": self.own_bias.arrays(),
        }
        return state_format.pack(meta, arrays)


def _decode(blob: bytes) -> _SessionState:
    meta, arrays = state_format.unpack(blob)
    if meta.get("pipeline") != V2vCoopPipeline.name:
        raise state_format.StateFormatError(f"state belongs to pipeline {meta.get('pipeline')!r}")
    # A session stored before the GNSS bias and covariance intersection goes on as it was created.
    options = {**LEGACY_OPTIONS, **LEGACY_INTEGRITY, **LEGACY_CONSISTENCY, **meta["options"]}
    white = Bias.stationary(0.0)
    return _SessionState(
        options,
        bool(meta["initialised"]),
        meta["t"],
        int(meta["epochs"]),
        meta["odometer_t"],
        arrays["mean"],
        arrays["cov"],
        arrays["own_mean"],
        arrays["own_cov"],
        Bias.from_arrays(arrays["bias"]) if "bias" in arrays else white,
        Bias.from_arrays(arrays["own_bias"]) if "own_bias" in arrays else white.copy(),
        {str(k): float(v) for k, v in meta.get("held", {}).items()},
        {str(k): float(v) for k, v in meta.get("seen", {}).items()},
        ConsistencyScale.from_list(meta.get("consistency")),
    )


class V2vCoopPipeline(Pipeline):
    """GPS + DR + V2V ranging, with the neighbours' positions taken as exact or augmented."""

    name = "v2v_coop"
    description = (
        "GNSS fixes, gyro + odometer dead reckoning and V2V ranges (metres or time of arrival) to neighbour "
        "vehicles read from their sessions; the improved UKF augments their positions into the state "
        "(Qiao & Qu 2021)."
    )
    measurement_kinds = (
        GnssFixObservation.kind,
        GyroObservation.kind,
        OdometerObservation.kind,
        V2vRangeObservation.kind,
    )
    publishes_track = True

    def option_specs(self) -> list[OptionSpec]:
        return list(OPTION_SPECS)

    def resolve_options(self, options: Mapping[str, Any] | None) -> dict[str, Any]:
        return resolve_options(OPTION_SPECS, options)

    def create(self, options: Mapping[str, Any], initial: InitialState | None) -> bytes:
        options = dict(options)
        bias = Bias.stationary(options["gnss_bias_std"])
        if initial is None:
            return _SessionState(
                options,
                False,
                None,
                0,
                None,
                np.zeros(6),
                np.eye(6),
                np.zeros(6),
                np.eye(6),
                bias,
                bias.copy(),
            ).to_bytes()
        mean = np.array([initial.x, initial.vx, 0.0, initial.y, initial.vy, 0.0])
        cov = np.diag(np.square([initial.position_std, initial.velocity_std, _INITIAL_ACCEL_STD] * 2))
        return _SessionState(
            options, True, None, 0, None, mean, cov, mean.copy(), cov.copy(), bias, bias.copy()
        ).to_bytes()

    def summarise(self, state: bytes) -> StateSummary:
        session = _decode(state)
        return StateSummary(session.initialised, session.t, session.epochs, {}, session.options)

    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        session = _decode(state)
        _validate(session, observations)
        fixes = [_step(session, epoch, observations, environment) for epoch in group_by_time(observations)]
        return ensure_finite_fixes(fixes), session.to_bytes()


def _validate(session: _SessionState, observations: Sequence[Observation]) -> None:
    check_batch(V2vCoopPipeline.name, set(V2vCoopPipeline.measurement_kinds), session.t, observations)


def _step(
    session: _SessionState, epoch: list[int], observations: Sequence[Observation], environment: Environment
) -> Fix:
    options = session.options
    method = options["method"]
    t = observations[epoch[0]].t
    uses: dict[int, MeasurementUse] = {}
    fixes = [i for i in epoch if isinstance(observations[i], GnssFixObservation)]
    for i in fixes[1:]:
        uses[i] = MeasurementUse(i, "gnss_fix", False, "another gnss_fix at the same time was used")
    if not session.initialised:
        return _initialise(session, epoch, observations, fixes, uses, t)
    dt = 0.0 if session.t is None else t - session.t
    # The gps method's fix is the receiver's, with nothing to check it against: no bound.
    protection: Protection | None = Protection(None, UNAVAILABLE) if options["integrity"] else None
    if method == "gps":
        status = _gps_only(session, epoch, observations, fixes, uses, dt)
    else:
        cooperative = method in ("ukf", "aug_ukf")
        # The fix's filter, and for the cooperative methods the GNSS + DR filter the vehicle shares.
        gaussians = [(session.mean, session.cov, session.bias)]
        if cooperative:
            gaussians.append((session.own_mean, session.own_cov, session.own_bias))
        updated = []
        used = False
        odometer_t = session.odometer_t
        for k, (mean, cov, bias) in enumerate(gaussians):
            session.odometer_t = odometer_t
            mean, cov, bias = _predict(options, mean, cov, bias, dt)
            if fixes:
                # fixes index the gnss_fix observations its isinstance filter found (cast: free at run time)
                gnss_fix = cast(GnssFixObservation, observations[fixes[0]])
                if k == 0:  # the fix's filter: its innovation tests its predicted covariance
                    session.consistency = observe(options, session.consistency, mean, cov, bias, gnss_fix)
                mean, cov, bias = _fix_update(options, mean, cov, bias, gnss_fix)
                uses[fixes[0]] = MeasurementUse(fixes[0], "gnss_fix", True)
                used = True
            prior_mean, prior_cov = mean, cov
            mean, cov, dr_used = _dr_update(session, mean, cov, epoch, observations, uses, t)
            if dr_used:
                bias = gnss_bias.condition(bias, prior_mean, prior_cov, mean, cov)
            updated.append((mean, cov, bias))
            used = used or dr_used
        session.mean, session.cov, session.bias = updated[0]
        ranges: list[tuple[int, RangeSource]] = []
        before = (session.mean, session.cov, session.bias)
        screened, unexcluded = frozenset[str](), False
        if cooperative:
            session.own_mean, session.own_cov, session.own_bias = updated[1]
            if options["integrity"]:
                screened, unexcluded = screen_neighbours(
                    options, session.held, session.seen, epoch, observations, environment, t, uses
                )
            ranges = _range_update(session, epoch, observations, uses, environment, t, screened)
            used = bool(ranges) or used
        else:
            session.own_mean, session.own_cov, session.own_bias = session.mean, session.cov, session.bias
        status = "tracking" if used else "predicted"
        if options["integrity"]:

            def redo(excluded: frozenset[str]) -> list[tuple[int, RangeSource]]:
                session.mean, session.cov, session.bias = before
                return _range_update(session, epoch, observations, uses, environment, t, screened | excluded)

            epoch_fix = cast(GnssFixObservation, observations[fixes[0]]) if fixes else None
            protection = monitor(
                options,
                lambda: (
                    float(session.mean[0]),
                    float(session.mean[3]),
                    session.cov[np.ix_([0, 3], [0, 3])].tolist(),
                ),
                lambda x, y: fix_source(options, session.bias, epoch_fix, x, y),
                ranges,
                redo,
                uses,
                session.held,
                t,
                *protection_scale(options, session.consistency),
            )
            if unexcluded:  # a neighbour's track failed its test and exclusion is off
                protection = dataclasses.replace(protection, state=ALARM)
    for i in epoch:
        if i not in uses:
            uses[i] = MeasurementUse(
                i, observations[i].kind, False, f"method {method} does not use {observations[i].kind}"
            )
    session.t = t
    session.epochs += 1
    # The gps method's fix is the receiver's, reported with the receiver's std.
    scale = 1.0 if method == "gps" else factor(options, session.consistency)
    reported = scaled_position(session.cov, (0, 3), scale)
    fix = kinematic_fix(t, status, session.mean, reported, [uses[i] for i in epoch])
    fix = with_protection(fix, protection)
    if method in ("ukf", "aug_ukf"):
        fix = dataclasses.replace(fix, shared=shared_point(t, session.own_mean, session.own_cov))
    elif scale != 1.0:  # neighbours get the filter's own covariance, as without the scale
        fix = dataclasses.replace(fix, shared=shared_point(t, session.mean, session.cov))
    return fix


def _initialise(
    session: _SessionState,
    epoch: list[int],
    observations: Sequence[Observation],
    fixes: list[int],
    uses: dict[int, MeasurementUse],
    t: float,
) -> Fix:
    """Start from the epoch's first GNSS fix, with a wide velocity."""
    for i in epoch:
        observation = observations[i]
        if isinstance(observation, OdometerObservation) and observation.distance is not None:
            session.odometer_t = t
    session.t = t
    session.epochs += 1
    if not fixes:
        for i in epoch:
            uses[i] = MeasurementUse(
                i, observations[i].kind, False, "no estimate yet: waiting for a gnss_fix to start from"
            )
        return Fix(t, "uninitialised", measurements=[uses[i] for i in epoch])
    first = cast(GnssFixObservation, observations[fixes[0]])  # fixes: the epoch's gnss_fix observations
    session.mean, session.cov, session.bias = _start(session.options, first)
    session.own_mean, session.own_cov, session.own_bias = (
        session.mean.copy(),
        session.cov.copy(),
        session.bias.copy(),
    )
    session.initialised = True
    for i in epoch:
        if i == fixes[0]:
            uses[i] = MeasurementUse(i, "gnss_fix", True)
        elif i not in uses:
            uses[i] = MeasurementUse(
                i, observations[i].kind, False, "the session starts from this epoch's first gnss_fix"
            )
    return kinematic_fix(t, "initialised", session.mean, session.cov, [uses[i] for i in epoch])


def _gps_only(
    session: _SessionState,
    epoch: list[int],
    observations: Sequence[Observation],
    fixes: list[int],
    uses: dict[int, MeasurementUse],
    dt: float,
) -> str:
    """The paper's GPS row: the fix as it is. Between fixes the last fix moves on at the velocity of a
    Kalman filter on the fixes alone (kept in ``own_mean``/``own_cov``, which this method shares with
    nobody), with the spread that velocity's uncertainty adds. Differencing consecutive fixes instead
    divides their noise by the interval: 3.8 m fixes 0.2 s apart give velocities 27 m/s off, and a
    fix extrapolated on them drifts tens of metres away while its covariance stays small."""
    options = session.options
    if dt > 0.0:
        session.own_mean, session.own_cov, session.own_bias = _predict(
            options, session.own_mean, session.own_cov, session.own_bias, dt
        )
        session.mean, session.cov = _KF.predict(
            session.mean, session.cov, ConstantAcceleration(options["accel_std"]), dt
        )
    if not fixes:
        return "predicted"
    obs = cast(GnssFixObservation, observations[fixes[0]])  # fixes: the epoch's gnss_fix observations
    std = obs.std if obs.std is not None else options["gps_std"]
    position = np.array([obs.x, obs.y])
    session.own_mean, session.own_cov, session.own_bias = _fix_update(
        options, session.own_mean, session.own_cov, session.own_bias, obs
    )
    # The fix with its own variance, beside the filter's velocity and acceleration (their correlation
    # with this one fix is left out: the filter's velocity rests on many fixes).
    mean, cov = session.own_mean.copy(), session.own_cov.copy()
    mean[[0, 3]] = position
    cov[[0, 3], :] = 0.0
    cov[:, [0, 3]] = 0.0
    cov[[0, 3], [0, 3]] = std**2
    session.mean, session.cov = mean, cov
    uses[fixes[0]] = MeasurementUse(fixes[0], "gnss_fix", True)
    return "tracking"


def _start(options: Mapping[str, Any], fix: GnssFixObservation) -> tuple[np.ndarray, np.ndarray, Bias]:
    """The state from a first fix z = p + b + v: position z with the bias's and the white variance,
    its error -(b + v) correlated with the bias (cross-covariance -sigma_b^2), a wide velocity."""
    std = fix.std if fix.std is not None else options["gps_std"]
    sigma = options["gnss_bias_std"]
    white = gnss_bias.white_variance(std, sigma) if sigma > 0.0 else std * std
    mean = np.array([fix.x, 0.0, 0.0, fix.y, 0.0, 0.0])
    cov = np.diag(np.square([0.0, _INITIAL_VELOCITY_STD, _INITIAL_ACCEL_STD] * 2))
    cov[0, 0] = cov[3, 3] = sigma * sigma + white
    bias = Bias.stationary(sigma)
    bias.cross[[0, 3], [0, 1]] = -sigma * sigma
    return mean, cov, bias


def _predict(
    options: Mapping[str, Any], mean: FloatArray, cov: FloatArray, bias: Bias, dt: float
) -> tuple[np.ndarray, np.ndarray, Bias]:
    """The nearly-constant-acceleration prediction over ``dt``, the GNSS bias's Gauss-Markov step beside it."""
    if dt <= 0.0:
        return mean, cov, bias
    motion = ConstantAcceleration(options["accel_std"])
    transition = motion.transition_matrix(mean, dt)
    mean, cov = _KF.predict(mean, cov, motion, dt)
    return (
        mean,
        cov,
        gnss_bias.predict(bias, transition, options["gnss_bias_tau"], options["gnss_bias_std"], dt),
    )


def _fix_update(
    options: Mapping[str, Any], mean: FloatArray, cov: FloatArray, bias: Bias, obs: GnssFixObservation
) -> tuple[np.ndarray, np.ndarray, Bias]:
    """The fix as position + Gauss-Markov bias + white noise (white alone when gnss_bias_std is 0)."""
    std = obs.std if obs.std is not None else options["gps_std"]
    position = np.array([obs.x, obs.y])
    sigma = options["gnss_bias_std"]
    if sigma <= 0.0:
        mean, cov, _, _ = _KF.update_one(mean, cov, KINEMATIC, GnssPosition(std), position)
        return mean, cov, bias
    return gnss_bias.fix_update(mean, cov, bias, position, gnss_bias.white_variance(std, sigma))


def _dr_update(
    session: _SessionState,
    mean: FloatArray,
    cov: FloatArray,
    epoch: list[int],
    observations: Sequence[Observation],
    uses: dict[int, MeasurementUse],
    t: float,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Gyro and odometer once the heading is known (see kinematic.heading_known); the UKF methods update
    through the UKF, gps_dr through the linearised Kalman filter."""
    options = session.options
    if not heading_known(mean, cov):
        session.odometer_t = wait_for_heading(epoch, observations, uses, session.odometer_t, t)
        return mean, cov, False
    filt = _KF if options["method"] == "gps_dr" else _UKF
    outcome = dead_reckoning_update(
        filt,
        mean,
        cov,
        epoch,
        observations,
        uses,
        session.odometer_t,
        options["gyro_std"],
        options["odometer_std"],
    )
    session.odometer_t = outcome.odometer_t
    return outcome.mean, outcome.cov, outcome.used


def _range_update(
    session: _SessionState,
    epoch: list[int],
    observations: Sequence[Observation],
    uses: dict[int, MeasurementUse],
    environment: Environment,
    t: float,
    excluded: frozenset[str],
) -> list[tuple[int, RangeSource]]:
    """V2V ranges to the neighbours available at ``t`` but ``excluded``: exact points (ukf) or augmented
    (aug_ukf). Returns the ranges used with the 1-sigma the update gave each (for the fault monitor)."""
    options = session.options
    points, point_covs, values, used = [], [], [], []
    for i in epoch:
        obs = observations[i]
        if not isinstance(obs, V2vRangeObservation) or obs.peer_vehicle_id in excluded:
            continue
        try:
            neighbour = position_at(
                environment.neighbour(obs.peer_vehicle_id),
                t,
                options["max_neighbour_age"],
                options["neighbour_accel_std"],
                environment.vehicle_id,
                obs.peer_vehicle_id,
            )
        except NeighbourUnavailable as reason:
            uses[i] = MeasurementUse(i, obs.kind, False, str(reason))
            continue
        points.append(neighbour.position)
        point_covs.append(neighbour.cov)
        values.append(obs.metres)
        used.append(i)
    if not used:
        return []
    points_array = np.array(points)
    observed = np.array(values)
    range_std = options["range_std"]
    count = len(used)
    noise = np.eye(count) * range_std**2
    extra_cov = np.zeros((2 * count, 2 * count))
    for k, cov in enumerate(point_covs):
        extra_cov[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = cov
    # Covariance intersection: the neighbours' estimates and this one share GNSS errors (and, through
    # earlier ranges, one another's): each is weighted for an unknown correlation, never as independent.
    offsets = session.mean[[0, 3]] - points_array
    directions = offsets / np.maximum(np.linalg.norm(offsets, axis=1), 1e-9)[:, None]
    design = np.zeros((count, 6))
    design[:, 0], design[:, 3] = directions[:, 0], directions[:, 1]
    neighbour_design = np.zeros((count, 2 * count))
    for k in range(count):
        neighbour_design[k, 2 * k : 2 * k + 2] = -directions[k]
    independent = options["neighbour_fusion"] == "independent"
    weight = (
        1.0 if independent else range_weight(session.cov, design, neighbour_design, extra_cov, noise, count)
    )
    if weight >= 1.0 and not independent:
        for i in used:
            uses[i] = MeasurementUse(
                i, "v2v_range", False, "covariance intersection gives the ranges no weight here"
            )
        return []
    prior_mean, prior_cov = session.mean, session.cov / weight
    bias = Bias(session.bias.mean, session.bias.cov / weight, session.bias.cross / weight)
    inflation = 1.0 if independent else count / (1.0 - weight)
    extra_cov = extra_cov * inflation
    if options["method"] == "ukf":
        # The neighbours as points; intersected, their covariance along the line of sight is added to the
        # range's; taken as independent, they are exact (the paper's traditional UKF).
        spread = (
            0.0
            if independent
            else np.einsum("ki,kij,kj->k", directions, np.array(point_covs), directions) * inflation
        )
        model = RsuRange(points_array, np.sqrt(range_std**2 + spread))
        session.mean, session.cov, _, _ = _UKF.update_one(prior_mean, prior_cov, KINEMATIC, model, observed)
    else:

        def ranges(states: np.ndarray) -> np.ndarray:
            own = states[:, [0, 3]]
            peers = states[:, 6:].reshape(states.shape[0], count, 2)
            distances: FloatArray = np.linalg.norm(peers - own[:, None, :], axis=2)
            return distances

        session.mean, session.cov, _, _ = augmented_update(
            _UKF,
            prior_mean,
            prior_cov,
            points_array.reshape(-1),
            extra_cov,
            ranges,
            noise,
            observed,
        )
    session.bias = gnss_bias.condition(bias, prior_mean, prior_cov, session.mean, session.cov)
    for i in used:
        uses[i] = MeasurementUse(i, "v2v_range", True)
    exact = independent and options["method"] == "ukf"
    spreads = (
        np.zeros(count) if exact else np.einsum("ki,kij,kj->k", directions, np.array(point_covs), directions)
    )
    stds = np.sqrt(range_std**2 + spreads * inflation)
    return [
        (
            i,
            RangeSource(
                cast(V2vRangeObservation, observations[i]).peer_vehicle_id,
                (float(points_array[k, 0]), float(points_array[k, 1])),
                float(observed[k]),
                float(stds[k]),
            ),
        )
        for k, i in enumerate(used)
    ]
