"""Pipeline ``v2x_federated``: the federated GPS / DR / V2X filter of Wang et al. 2019.

Three sub-filters on the paper's state [e, ve, ae, n, vn, an] (the kinematic block of the core
layout), each predicted with the "current statistical" model:

* GPS: a Kalman filter on ``gnss_fix`` positions (eqs. 3-6);
* DR: a square-root UKF on gyro yaw rate and odometer distance (eqs. 7-10);
* V2X: a square-root UKF on ranges to RSUs (``rsu_range``) and to neighbour vehicles
  (``v2v_range``, their positions read from their sessions' published tracks) (eqs. 11-14).

Each epoch the better of GPS and V2X, by the trace of its covariance, is fused with DR (eq. 15);
with feedback on, the fused estimate resets all three sub-filters with information-sharing factors
(eq. 16): P_i = P / beta_i, and each sub-filter's process noise is Q / beta_i (beta_G/V + beta_D = 1).
With feedback off the sub-filters run independently and the fused estimate is output only.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from edgepos.core import gnss_bias, layout
from edgepos.core import state as state_format
from edgepos.core.consistency import ConsistencyScale, scaled_position
from edgepos.core.cooperative_integrity import RangeSource
from edgepos.core.errors import NumericalError
from edgepos.core.filters.ekf import ExtendedKalmanFilter
from edgepos.core.filters.srukf import SquareRootUnscentedKalmanFilter
from edgepos.core.gnss_bias import Bias
from edgepos.core.integrity import ALARM, Protection
from edgepos.core.intersection import range_weight
from edgepos.core.measurements.base import MeasurementModel
from edgepos.core.measurements.gnss_fix import GnssPosition
from edgepos.core.motion.current_statistical import CurrentStatistical
from edgepos.core.numerics import FloatArray
from edgepos.core.observations import (
    GnssFixObservation,
    GyroObservation,
    Observation,
    OdometerObservation,
    RsuRangeObservation,
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
    check_batch,
    dead_reckoning_update,
    kinematic_fix,
    shared_point,
    wait_for_heading,
)
from edgepos.pipelines.options import resolve_options
from edgepos.pipelines.tracks import NeighbourUnavailable, position_at

SUB_FILTERS = ("gps", "dr", "v2x")
_KIN = layout.KINEMATIC
_INITIAL_VELOCITY_STD = 10.0
_INITIAL_ACCEL_STD = 1.0
CONSISTENCY_DEFAULT = False

OPTION_SPECS = (
    OptionSpec(
        "feedback", "boolean", True, "Reset the sub-filters with the fused estimate each epoch (eq. 16)."
    ),
    OptionSpec(
        "dr_share",
        "number",
        0.5,
        "Information-sharing factor beta_D of the DR sub-filter; beta_G/V = 1 - beta_D (eq. 16).",
        minimum=0.05,
        maximum=0.95,
    ),
    OptionSpec(
        "gps_std",
        "number",
        math.sqrt(15.0),
        "GNSS fix total error 1-sigma per axis (m) when a fix carries none; gnss_bias_std of it is the "
        "time-correlated part, the rest white.",
        minimum=1e-3,
        maximum=1e4,
    ),
    *GNSS_BIAS_SPECS,
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
        3.0,
        "Range 1-sigma (m) to RSUs and neighbour vehicles.",
        minimum=1e-3,
        maximum=1e4,
    ),
    OptionSpec(
        "cs_alpha",
        "number",
        0.1,
        "Current-statistical manoeuvre frequency 1/tau (1/s).",
        minimum=1e-4,
        maximum=100.0,
    ),
    OptionSpec(
        "cs_a_max",
        "number",
        10.0,
        "Current-statistical maximum manoeuvre acceleration (m/s^2).",
        minimum=0.1,
        maximum=100.0,
    ),
    *neighbour_specs(
        "How a neighbour's estimate enters the V2X sub-filter's range update: intersection (covariance "
        "intersection with the sub-filter's estimate: consistent whatever their correlation, e.g. GNSS "
        "errors they share or earlier ranges between them) or independent (its covariance added to the "
        "range's as independent noise, the paper's reading)."
    ),
    *COOPERATIVE_INTEGRITY_SPECS,
    *consistency_specs(
        CONSISTENCY_DEFAULT,
        "the fused estimate's, with feedback on; with feedback off the fix's innovation tests the GPS "
        "sub-filter, not the fused estimate, and the fix is reported as the filter gives it",
    ),
)


class SharedNoiseCurrentStatistical(CurrentStatistical):
    """The current-statistical model with its process noise scaled by 1/beta (eq. 16's Q_i)."""

    def __init__(self, alpha: float, a_max: float, noise_scale: float) -> None:
        super().__init__(alpha=alpha, a_max=a_max)
        self.noise_scale = float(noise_scale)

    def noise_covariance(self, mean: np.ndarray, dt: float) -> np.ndarray:
        return self.noise_scale * super().noise_covariance(mean, dt)


class RangesToPoints(MeasurementModel):
    """Ranges (m) to known points (eq. 12), with per-range noise variances (m^2)."""

    def __init__(self, points: np.ndarray, variances: np.ndarray) -> None:
        self.points = np.asarray(points, dtype=float).reshape(-1, 2)
        self._noise = np.diag(np.asarray(variances, dtype=float))

    @property
    def dim(self) -> int:
        return self.points.shape[0]

    @property
    def angle_mask(self) -> np.ndarray:
        return np.zeros(self.dim, dtype=bool)

    def predict(self, states: np.ndarray) -> np.ndarray:
        dx = states[:, None, layout.XP] - self.points[None, :, 0]
        dy = states[:, None, layout.YP] - self.points[None, :, 1]
        ranges: FloatArray = np.hypot(dx, dy)
        return ranges

    def jacobian(self, states: np.ndarray) -> np.ndarray:
        dx = states[:, None, layout.XP] - self.points[None, :, 0]
        dy = states[:, None, layout.YP] - self.points[None, :, 1]
        distance = np.maximum(np.hypot(dx, dy), 1e-9)
        jacobian = np.zeros((states.shape[0], self.dim, layout.FULL_DIM))
        jacobian[:, :, layout.XP] = dx / distance
        jacobian[:, :, layout.YP] = dy / distance
        return jacobian

    def noise_covariance(self) -> np.ndarray:
        return self._noise


@dataclass
class _SessionState:
    options: dict[str, Any]
    initialised: bool
    t: float | None
    epochs: int
    odometer_t: float | None  # time of the last odometer distance reading (start of the next interval)
    means: np.ndarray  # (3, 6): gps, dr, v2x sub-filter means
    covs: np.ndarray  # (3, 6, 6)
    noise_scales: np.ndarray  # (3,): each sub-filter's process-noise factor 1/beta_i (1 without feedback)
    bias: Bias  # the GNSS fix error's Gauss-Markov part, beside the GPS sub-filter
    dr_started: bool = False  # a fix after the first has given the filter a velocity (see _dr_update)
    held: dict[str, float] = dataclasses.field(default_factory=dict)  # sources held out: id -> until t
    seen: dict[str, float] = dataclasses.field(default_factory=dict)  # neighbours' last track point tested
    # the fused estimate's, from the GNSS fix innovations (with feedback)
    consistency: ConsistencyScale = dataclasses.field(default_factory=ConsistencyScale)

    def to_bytes(self) -> bytes:
        meta = {
            "pipeline": V2xFederatedPipeline.name,
            "options": self.options,
            "initialised": self.initialised,
            "t": self.t,
            "epochs": self.epochs,
            "odometer_t": self.odometer_t,
            "dr_started": self.dr_started,
            "held": self.held,
            "seen": self.seen,
            "consistency": self.consistency.to_list(),
        }
        arrays = {
            "means": self.means,
            "covs": self.covs,
            "noise_scales": self.noise_scales,
            "bias": self.bias.arrays(),
        }
        return state_format.pack(meta, arrays)


def _decode(blob: bytes) -> _SessionState:
    meta, arrays = state_format.unpack(blob)
    if meta.get("pipeline") != V2xFederatedPipeline.name:
        raise state_format.StateFormatError(f"state belongs to pipeline {meta.get('pipeline')!r}")
    # A session stored before the GNSS bias and covariance intersection goes on as it was created.
    return _SessionState(
        {**LEGACY_OPTIONS, **LEGACY_INTEGRITY, **LEGACY_CONSISTENCY, **meta["options"]},
        bool(meta["initialised"]),
        meta["t"],
        int(meta["epochs"]),
        meta["odometer_t"],
        arrays["means"],
        arrays["covs"],
        arrays["noise_scales"],
        Bias.from_arrays(arrays["bias"]) if "bias" in arrays else Bias.stationary(0.0),
        bool(meta.get("dr_started", True)),
        {str(k): float(v) for k, v in meta.get("held", {}).items()},
        {str(k): float(v) for k, v in meta.get("seen", {}).items()},
        ConsistencyScale.from_list(meta.get("consistency")),
    )


class V2xFederatedPipeline(Pipeline):
    """Federated GPS (KF) / DR (SRUKF) / V2X ranging (SRUKF) filter with fusion-feedback."""

    publishes_track = True

    name = "v2x_federated"
    description = (
        "GNSS fixes, gyro + odometer dead reckoning and V2X ranges to RSUs or neighbour vehicles, each in its "
        "own sub-filter; the better of GNSS and V2X fused with DR and fed back (Wang et al. 2019)."
    )
    measurement_kinds = (
        GnssFixObservation.kind,
        GyroObservation.kind,
        OdometerObservation.kind,
        RsuRangeObservation.kind,
        V2vRangeObservation.kind,
    )

    def option_specs(self) -> list[OptionSpec]:
        return list(OPTION_SPECS)

    def resolve_options(self, options: Mapping[str, Any] | None) -> dict[str, Any]:
        return resolve_options(OPTION_SPECS, options)

    def create(self, options: Mapping[str, Any], initial: InitialState | None) -> bytes:
        options = dict(options)
        scales = np.full(3, 1.0)
        if options["feedback"]:
            scales = _feedback_scales(options)
        bias = Bias.stationary(options["gnss_bias_std"])
        if initial is None:
            return _SessionState(
                options, False, None, 0, None, np.zeros((3, 6)), np.tile(np.eye(6), (3, 1, 1)), scales, bias
            ).to_bytes()
        mean = np.array([initial.x, initial.vx, 0.0, initial.y, initial.vy, 0.0])
        stds = [initial.position_std, initial.velocity_std, _INITIAL_ACCEL_STD] * 2
        cov = np.diag(np.square(stds))
        return _SessionState(
            options, True, None, 0, None, np.tile(mean, (3, 1)), np.tile(cov, (3, 1, 1)), scales, bias
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


# -- validation ----------------------------------------------------------------------------------


def _validate(session: _SessionState, observations: Sequence[Observation]) -> None:
    check_batch(
        V2xFederatedPipeline.name, set(V2xFederatedPipeline.measurement_kinds), session.t, observations
    )


# -- one epoch -----------------------------------------------------------------------------------

_KF = ExtendedKalmanFilter()  # exact Kalman filter: motion and GNSS fix are linear
_SRUKF = SquareRootUnscentedKalmanFilter()


def _feedback_scales(options: Mapping[str, Any]) -> np.ndarray:
    beta_d = float(options["dr_share"])
    return np.array([1.0 / (1.0 - beta_d), 1.0 / beta_d, 1.0 / (1.0 - beta_d)])


def _step(
    session: _SessionState, epoch: list[int], observations: Sequence[Observation], environment: Environment
) -> Fix:
    options = session.options
    t = observations[epoch[0]].t
    uses: dict[int, MeasurementUse] = {}
    if not session.initialised:
        fixes = [i for i in epoch if isinstance(observations[i], GnssFixObservation)]
        if not fixes:
            for i in epoch:
                uses[i] = MeasurementUse(
                    i, observations[i].kind, False, "no estimate yet: waiting for a gnss_fix to start from"
                )
                _note_odometer(session, observations[i])
            session.t = t
            session.epochs += 1
            return Fix(t, "uninitialised", measurements=[uses[i] for i in epoch])
        first = cast(GnssFixObservation, observations[fixes[0]])  # fixes: the epoch's gnss_fix observations
        std = first.std if first.std is not None else options["gps_std"]
        sigma = options["gnss_bias_std"]
        white = gnss_bias.white_variance(std, sigma) if sigma > 0.0 else std * std
        mean = np.array([first.x, 0.0, 0.0, first.y, 0.0, 0.0])
        cov = np.diag(np.square([0.0, _INITIAL_VELOCITY_STD, _INITIAL_ACCEL_STD] * 2))
        cov[0, 0] = cov[3, 3] = sigma * sigma + white
        session.means[:] = mean
        session.covs[:] = cov
        # The first fix's error is -(bias + white): correlated with the bias by -sigma^2.
        session.bias = Bias.stationary(sigma)
        session.bias.cross[[0, 3], [0, 1]] = -sigma * sigma
        session.initialised = True
        session.t = t
        session.epochs += 1
        for i in epoch:
            used = i == fixes[0]
            uses[i] = MeasurementUse(
                i,
                observations[i].kind,
                used,
                None if used else "the session starts from this epoch's first gnss_fix",
            )
            _note_odometer(session, observations[i])
        return kinematic_fix(t, "initialised", session.means[0], session.covs[0], [uses[i] for i in epoch])

    dt = 0.0 if session.t is None else t - session.t
    means, covs = session.means.copy(), session.covs.copy()
    bias = session.bias
    if dt > 0.0:
        for k, filt in enumerate((_KF, _SRUKF, _SRUKF)):
            model = SharedNoiseCurrentStatistical(
                options["cs_alpha"], options["cs_a_max"], session.noise_scales[k]
            )
            if k == 0:
                transition = model.transition_matrix(means[0], dt)
                bias = gnss_bias.predict(
                    bias, transition, options["gnss_bias_tau"], options["gnss_bias_std"], dt
                )
            means[k], covs[k] = filt.predict(means[k], covs[k], model, dt)

    updated = [False, False, False]
    epoch_fixes = [i for i in epoch if isinstance(observations[i], GnssFixObservation)]
    if options["feedback"] and epoch_fixes:
        # With feedback the GPS sub-filter's prediction is the fused one times its noise scale 1/beta.
        session.consistency = observe(
            options,
            session.consistency,
            means[0],
            covs[0],
            bias,
            cast(GnssFixObservation, observations[epoch_fixes[0]]),  # the epoch's first gnss_fix
            float(session.noise_scales[0]),
        )
    gps, bias = _gps_update(means, covs, bias, epoch, observations, options, uses)
    updated[0] = gps
    session.dr_started = session.dr_started or gps
    updated[1] = _dr_update(session, means, covs, epoch, observations, options, uses, t)
    v2x_prior = (means[2].copy(), covs[2].copy())
    screened, unexcluded = frozenset[str](), False
    if options["integrity"]:
        screened, unexcluded = screen_neighbours(
            options, session.held, session.seen, epoch, observations, environment, t, uses
        )
    ranges = _v2x_update(means, covs, epoch, observations, options, uses, environment, t, screened)
    updated[2] = bool(ranges)

    chosen = 0 if np.trace(covs[0]) <= np.trace(covs[2]) else 2
    fused_mean, fused_cov = fuse(means[chosen], covs[chosen], means[1], covs[1])
    protection: Protection | None = None
    if options["integrity"]:

        def redo(excluded: frozenset[str]) -> list[tuple[int, RangeSource]]:
            nonlocal chosen, fused_mean, fused_cov
            means[2], covs[2] = v2x_prior[0].copy(), v2x_prior[1].copy()
            kept = _v2x_update(
                means, covs, epoch, observations, options, uses, environment, t, screened | excluded
            )
            updated[2] = bool(kept)
            chosen = 0 if np.trace(covs[0]) <= np.trace(covs[2]) else 2
            fused_mean, fused_cov = fuse(means[chosen], covs[chosen], means[1], covs[1])
            return kept if chosen == 2 else []

        # The fused fix rests on DR and the chosen sub-filter: its sources are that sub-filter's.
        fixes = [i for i in epoch if isinstance(observations[i], GnssFixObservation)]
        epoch_fix = cast(GnssFixObservation, observations[fixes[0]]) if fixes else None
        protection = monitor(
            options,
            lambda: (float(fused_mean[0]), float(fused_mean[3]), fused_cov[np.ix_([0, 3], [0, 3])].tolist()),
            lambda x, y: fix_source(options, bias, epoch_fix if chosen == 0 else None, x, y),
            ranges if chosen == 2 else [],
            redo,
            uses,
            session.held,
            t,
            *protection_scale(options, session.consistency, applies=bool(options["feedback"])),
        )
        if unexcluded:  # a neighbour's track failed its test and exclusion is off
            protection = dataclasses.replace(protection, state=ALARM)
    if options["feedback"]:
        scales = _feedback_scales(options)
        before_mean, before_cov = means[0].copy(), covs[0].copy()
        for k in range(3):
            means[k] = fused_mean
            covs[k] = fused_cov * scales[k]
        # The GPS sub-filter's bias follows the reset of its kinematic state (its regression on it kept).
        bias = gnss_bias.condition(bias, before_mean, before_cov, means[0], covs[0])
    session.means, session.covs, session.bias = means, covs, bias
    session.t = t
    session.epochs += 1
    status = "tracking" if any(updated) else "predicted"
    scale = factor(options, session.consistency)
    reported = scaled_position(fused_cov, (0, 3), scale)
    fix = with_protection(
        kinematic_fix(t, status, fused_mean, reported, [uses[i] for i in epoch]), protection
    )
    if scale != 1.0:  # neighbours get the filter's own covariance, as without the scale
        fix = dataclasses.replace(fix, shared=shared_point(t, fused_mean, fused_cov))
    return fix


def _note_odometer(session: _SessionState, obs: Observation) -> None:
    if isinstance(obs, OdometerObservation) and obs.distance is not None:
        session.odometer_t = obs.t


def _gps_update(
    means: FloatArray,
    covs: FloatArray,
    bias: Bias,
    epoch: list[int],
    observations: Sequence[Observation],
    options: Mapping[str, Any],
    uses: dict[int, MeasurementUse],
) -> tuple[bool, Bias]:
    """The fix as position + Gauss-Markov bias + white noise (white alone when gnss_bias_std is 0)."""
    fixes = [i for i in epoch if isinstance(observations[i], GnssFixObservation)]
    for i in fixes[1:]:
        uses[i] = MeasurementUse(i, "gnss_fix", False, "another gnss_fix at the same time was used")
    if not fixes:
        return False, bias
    obs = cast(GnssFixObservation, observations[fixes[0]])  # fixes: the epoch's gnss_fix observations
    std = obs.std if obs.std is not None else options["gps_std"]
    position = np.array([obs.x, obs.y])
    sigma = options["gnss_bias_std"]
    if sigma > 0.0:
        means[0], covs[0], bias = gnss_bias.fix_update(
            means[0], covs[0], bias, position, gnss_bias.white_variance(std, sigma)
        )
    else:
        means[0], covs[0], _, _ = _KF.update_one(means[0], covs[0], _KIN, GnssPosition(std), position)
    uses[fixes[0]] = MeasurementUse(fixes[0], "gnss_fix", True)
    return True, bias


def _dr_update(
    session: _SessionState,
    means: FloatArray,
    covs: FloatArray,
    epoch: list[int],
    observations: Sequence[Observation],
    options: Mapping[str, Any],
    uses: dict[int, MeasurementUse],
    t: float,
) -> bool:
    """Gyro and odometer once a second fix has given the filter a velocity (``session.dr_started``):
    from a start at rest with none, they pin the speed along an arbitrary axis (measured on the
    correlated-error scene with fixes every second: 11-18 m off for the first 20 s). The stricter rule
    of ``v2v_coop`` (speed 5 sigma of the velocity, ``kinematic.heading_known``) does not suit this
    filter: the feedback's 1/beta widens the DR sub-filter's velocity every epoch, and on the paper's
    scene it hovers at 1.5-2.5 sigma (waiting for 2 sigma cost 0.5 m under multipath there)."""
    if not session.dr_started:
        session.odometer_t = wait_for_heading(
            epoch,
            observations,
            uses,
            session.odometer_t,
            t,
            "no velocity yet: dead reckoning waits for a second gnss_fix",
        )
        return False
    outcome = dead_reckoning_update(
        _SRUKF,
        means[1],
        covs[1],
        epoch,
        observations,
        uses,
        session.odometer_t,
        options["gyro_std"],
        options["odometer_std"],
    )
    means[1], covs[1], session.odometer_t = outcome.mean, outcome.cov, outcome.odometer_t
    return outcome.used


def _v2x_update(
    means: FloatArray,
    covs: FloatArray,
    epoch: list[int],
    observations: Sequence[Observation],
    options: Mapping[str, Any],
    uses: dict[int, MeasurementUse],
    environment: Environment,
    t: float,
    excluded: frozenset[str],
) -> list[tuple[int, RangeSource]]:
    """Ranges to RSUs (known points) and neighbours (their published estimates, weighted by covariance
    intersection against this sub-filter: both rest on GNSS errors in common and on one another's
    ranges, so neither is taken as independent of the other), but those to ``excluded`` RSU or vehicle
    ids. Returns the ranges used with the 1-sigma the update gave each (for the fault monitor)."""
    points, variances, point_covs, used = [], [], [], []
    names: list[str] = []
    range_var = options["range_std"] ** 2
    for i in epoch:
        obs = observations[i]
        source = getattr(obs, "rsu_id", None) or getattr(obs, "peer_vehicle_id", None)
        if source in excluded:
            continue
        if isinstance(obs, RsuRangeObservation):
            rsu = environment.rsu(obs.rsu_id)
            if rsu is None:
                uses[i] = MeasurementUse(i, obs.kind, False, f"unknown RSU {obs.rsu_id!r}")
                continue
            point, point_cov = np.array([rsu.x, rsu.y]), np.zeros((2, 2))
            std = rsu.range_std if rsu.range_std is not None else options["range_std"]
            variance = std**2
            value = obs.range
        elif isinstance(obs, V2vRangeObservation):
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
            point, point_cov, variance = neighbour.position, neighbour.cov, range_var
            value = obs.metres
        else:
            continue
        offset = np.array([means[2][0], means[2][3]]) - point
        norm = float(np.hypot(*offset))
        direction = offset / norm if norm > 1e-9 else np.zeros(2)
        points.append(point)
        variances.append(variance)
        point_covs.append((direction, point_cov))
        used.append((i, value))
        names.append(str(source))
    if not used:
        return []
    count = len(used)
    neighbours = [k for k, (_, cov) in enumerate(point_covs) if np.any(cov)]
    design = np.zeros((count, 6))
    neighbour_design = np.zeros((count, 2 * count))
    neighbour_cov = np.zeros((2 * count, 2 * count))
    for k, (direction, cov) in enumerate(point_covs):
        design[k, 0], design[k, 3] = direction
        neighbour_design[k, 2 * k : 2 * k + 2] = -direction
        neighbour_cov[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = cov
    weight, scale = 1.0, 1.0  # independent: the neighbour's covariance as independent range noise
    if options["neighbour_fusion"] == "intersection" and neighbours:
        weight = range_weight(
            covs[2], design, neighbour_design, neighbour_cov, np.diag(variances), len(neighbours)
        )
        scale = len(neighbours) / (1.0 - weight) if weight < 1.0 else 0.0
    if weight >= 1.0 and scale == 0.0:
        # Intersected, the neighbours' ranges would carry no weight: only the RSUs' (exact points) are used.
        for k in neighbours:
            i, _ = used[k]
            uses[i] = MeasurementUse(
                i, observations[i].kind, False, "covariance intersection gives the range no weight here"
            )
        keep = [k for k in range(count) if k not in neighbours]
        if not keep:
            return []
        # one comprehension per list (not one over the four): each keeps its element type
        points = [points[k] for k in keep]
        variances = [variances[k] for k in keep]
        point_covs = [point_covs[k] for k in keep]
        used = [used[k] for k in keep]
        names = [names[k] for k in keep]
        weight = 1.0
    total = [
        v + scale * float(d @ c @ d) for v, (d, c) in zip(variances, point_covs)
    ]  # the nodes' own uncertainty
    model = RangesToPoints(np.array(points), np.array(total))
    means[2], covs[2], _, _ = _SRUKF.update_one(
        means[2], covs[2] / weight, _KIN, model, np.array([v for _, v in used])
    )
    for i, _ in used:
        uses[i] = MeasurementUse(i, observations[i].kind, True)
    return [
        (i, RangeSource(name, (float(p[0]), float(p[1])), float(value), math.sqrt(var)))
        for (i, value), name, p, var in zip(used, names, points, total, strict=True)
    ]


def fuse(
    mean_a: np.ndarray, cov_a: np.ndarray, mean_b: np.ndarray, cov_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 15: P = (Pa^-1 + Pb^-1)^-1, x = P (Pa^-1 xa + Pb^-1 xb), through Cholesky solves."""
    try:
        info_a = np.linalg.inv(np.linalg.cholesky(cov_a))
        info_b = np.linalg.inv(np.linalg.cholesky(cov_b))
    except np.linalg.LinAlgError:
        raise NumericalError("a sub-filter covariance is not positive definite; cannot fuse") from None
    info_a, info_b = info_a.T @ info_a, info_b.T @ info_b
    information = info_a + info_b
    try:
        chol = np.linalg.cholesky(0.5 * (information + information.T))
    except np.linalg.LinAlgError:
        raise NumericalError("fused information matrix is not positive definite") from None
    inverse_factor = np.linalg.inv(chol)
    cov = inverse_factor.T @ inverse_factor
    cov = 0.5 * (cov + cov.T)
    mean = cov @ (info_a @ mean_a + info_b @ mean_b)
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
        raise NumericalError("fused estimate is not finite")
    return mean, cov
