"""The RSU + IMU pipeline (Dai, Su, Cui, Wang 2025): RSU range/bearing and gyro yaw rate into an
IMM or 2IMM bank of EKF/UKF/CKF filters over the 8-dim vehicle state.

Per epoch (observations sharing a timestamp):
1. RSUs in view: the known RSUs whose measured range is inside their communication radius; the
   nearest ``max_rsus`` of them by measured range are used, the rest are reported as not used.
2. Optional Mahalanobis gate of each RSU pair (2 dof) and gyro reading (1 dof) against the bank's
   predicted output, linearised at the predicted mean.
3. ``rsu_handling="joint"``: one update with every RSU pair and the gyro stacked.
   ``"average"``: the paper's reading, one update per RSU (each with the gyro), posteriors averaged.

The bank steps on the compiled kernels when they cover its filter and models (``core.compiled``),
else on the numpy reference; both give the same fixes to rounding.
"""

from __future__ import annotations

import functools
import json
import math
import struct
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, cast

import numpy as np

from edgepos.core import layout
from edgepos.core import state as state_format
from edgepos.core.compiled import BankStepper, stepper_for
from edgepos.core.filters import GaussianFilter, make_filter
from edgepos.core.filters.sigma_points import SigmaPointFilter
from edgepos.core.imm import Gaussian, InteractingMultipleModel, Prediction, StepResult
from edgepos.core.integrity import Protection
from edgepos.core.integrity_bank import SeparationBank
from edgepos.core.motion import MotionModel, make_motion_model
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.core.updates import RsuGyroEpoch
from edgepos.pipelines.base import (
    Environment,
    Fix,
    InitialState,
    MeasurementUse,
    OptionSpec,
    Pipeline,
    PipelineInputError,
    Rsu,
    StateSummary,
    ensure_finite_fixes,
)
from edgepos.pipelines.integrity import bank_from_tail, monitored_update
from edgepos.pipelines.options import resolve_options
from edgepos.pipelines.rsu_imu_batch import (
    Batch,
    EpochParts,
    batch_epochs,
    batch_records,
    epoch_measurements,
    read_batch,
)
from edgepos.pipelines.rsu_imu_fix import epoch_fix
from edgepos.pipelines.rsu_imu_options import OPTION_SPECS, cross_check, parameter_problems
from edgepos.pipelines.rsu_imu_run import UNGATED, gate_threshold, gate_thresholds, run_fixes, used

#: Standard deviations of the components an initial state does not give (acceleration m/s^2,
#: heading rad, turn rate rad/s).
_INITIAL_ACCEL_STD = 3.0
_INITIAL_HEADING_STD = math.pi
_INITIAL_TURN_STD = 0.5


# The session's bytes, little-endian: magic, version, flags (_INITIALISED, _HAS_T, _HAS_FILTER_T), t and
# filter_t (0 when absent), epochs, the number of models, the length of the options' JSON text; then that
# text (UTF-8), the probabilities, means (models x 8) and covariances (models x 8 x 8) as float64. Read and
# written in a few microseconds (``core.state``'s JSON header, used before, cost about 25 us a batch both
# ways); states in that layout are still read (``_decode_json``).
_STATE = struct.Struct("<4sBBddqHI")
_MAGIC = b"EPRI"
_VERSION = 1
_INITIALISED, _HAS_T, _HAS_FILTER_T = 1, 2, 4
_ALL_FLAGS = _INITIALISED | _HAS_T | _HAS_FILTER_T
_FULL_COV = (layout.FULL_DIM, layout.FULL_DIM)
_FLOATS_PER_MODEL = 1 + layout.FULL_DIM + layout.FULL_DIM * layout.FULL_DIM


#: Per thread, the last batch ``process`` read and the observations it was read from.
_LAST_READ = threading.local()


@dataclass
class _SessionState:
    """The decoded session: the bank's per-model Gaussians, probabilities and the clock."""

    options: dict[str, Any]
    initialised: bool
    t: float | None  # time of the last epoch processed (also before initialisation)
    filter_t: float | None  # time the filter estimates refer to
    epochs: int
    probabilities: np.ndarray
    means: np.ndarray  # (models, 8), zero where a model lacks a component
    covs: np.ndarray  # (models, 8, 8)
    options_key: str = ""  # the options as sorted JSON: the bank's cache key and their stored form
    integrity_bank: SeparationBank | None = None  # the protection level's sub-filters (pipelines.integrity)

    def __post_init__(self) -> None:
        if not self.options_key:
            self.options_key = _options_key(self.options)

    def to_bytes(self) -> bytes:
        """The session in the binary layout of ``_STATE`` (see there). The options go in as their JSON
        text, and decoding looks the parsed options up by that text."""
        count = len(self.probabilities)
        arrays = {"probabilities": self.probabilities, "means": self.means, "covs": self.covs}
        shapes = {"probabilities": (count,), "means": (count, layout.FULL_DIM), "covs": (count, *_FULL_COV)}
        chunks = []
        for name, array in arrays.items():
            data = np.asarray(array, dtype="<f8")
            if data.shape != shapes[name]:
                raise ValueError(f"state array {name!r} has shape {data.shape}, not {shapes[name]}")
            chunks.append(data.tobytes())
        body = b"".join(chunks)
        values = np.frombuffer(body, dtype="<f8")
        # A state holding NaN is a bug to surface, never something to store. The sum of squares is finite
        # when every value is (one pass); only when it is not (NaN, or an overflow) is each value checked.
        if not math.isfinite(values.dot(values)) and not np.isfinite(values).all():
            bad = next(name for name, array in arrays.items() if not np.all(np.isfinite(array)))
            raise ValueError(f"state array {bad!r} is not finite")
        flags = (
            (_INITIALISED if self.initialised else 0)
            | (0 if self.t is None else _HAS_T)
            | (0 if self.filter_t is None else _HAS_FILTER_T)
        )
        t = 0.0 if self.t is None else self.t
        filter_t = 0.0 if self.filter_t is None else self.filter_t
        if not (math.isfinite(t) and math.isfinite(filter_t)):
            raise ValueError(f"state times are not finite: t={self.t!r}, filter_t={self.filter_t!r}")
        key = self.options_key.encode()
        header = _STATE.pack(_MAGIC, _VERSION, flags, t, filter_t, self.epochs, count, len(key))
        tail = b"" if self.integrity_bank is None else self.integrity_bank.to_bytes()
        return header + key + body + tail


class RsuImuPipeline(Pipeline):
    """RSU range + bearing and gyro yaw rate, IMM/2IMM over EKF, UKF or CKF (default 2IMM-CKF)."""

    name = "rsu_imu"
    description = (
        "Roadside-unit range and bearing plus gyro yaw rate, fused by a 2IMM bank of cubature Kalman filters "
        "over constant-acceleration, adaptive-turn and Singer models (Dai et al. 2025)."
    )
    measurement_kinds = (RsuObservation.kind, GyroObservation.kind)

    def option_specs(self) -> list[OptionSpec]:
        return list(OPTION_SPECS)

    def resolve_options(self, options: Mapping[str, Any] | None) -> dict[str, Any]:
        resolved = resolve_options(OPTION_SPECS, options)
        problems = cross_check(resolved)
        if problems:
            raise PipelineInputError(problems)
        problems = parameter_problems(resolved)  # build models and filter now, so bad parameters surface here
        if problems:
            raise PipelineInputError(problems)
        return resolved

    def create(self, options: Mapping[str, Any], initial: InitialState | None) -> bytes:
        options = dict(options)
        bank = _bank(_options_key(options))
        probabilities = _initial_probabilities(options, len(bank.models))
        if initial is None:
            means, covs = bank.initial(np.zeros(layout.FULL_DIM), np.eye(layout.FULL_DIM))
            return _SessionState(options, False, None, None, 0, probabilities, means, covs).to_bytes()
        heading = math.atan2(initial.vy, initial.vx) if math.hypot(initial.vx, initial.vy) > 0 else 0.0
        mean = np.array([initial.x, initial.vx, 0.0, initial.y, initial.vy, 0.0, heading, 0.0])
        stds = [
            initial.position_std,
            initial.velocity_std,
            _INITIAL_ACCEL_STD,
            initial.position_std,
            initial.velocity_std,
            _INITIAL_ACCEL_STD,
            _INITIAL_HEADING_STD,
            _INITIAL_TURN_STD,
        ]
        means, covs = bank.initial(mean, np.diag(np.square(stds)))
        return _SessionState(options, True, None, None, 0, probabilities, means, covs).to_bytes()

    def summarise(self, state: bytes) -> StateSummary:
        session = _decode(state)
        names = session.options["models"]
        return StateSummary(
            initialised=session.initialised,
            t=session.t,
            epochs=session.epochs,
            model_probabilities=dict(zip(names, map(float, session.probabilities))),
            options=session.options,
        )

    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        session = _decode(state)
        batch = read_batch(session.options, session.t, observations, environment)
        _LAST_READ.batch = (observations, batch)  # for written_records
        bank = _bank(session.options_key)
        stepper = _stepper(bank)
        epochs = batch_epochs(observations, batch, session.options)
        fixes: list[Fix] = []
        k = 0
        while k < len(epochs):  # runs of usual epochs in one compiled call, the others one by one
            run = run_fixes(session, bank, stepper, epochs, k, observations)  # finite: bounded in the run
            if run:
                fixes += run
                k += len(run)
            else:
                fixes += ensure_finite_fixes([_step(session, bank, epochs.part(k), observations, batch)])
                k += 1
        return fixes, session.to_bytes()

    def written_records(self, observations: Sequence[Observation]) -> tuple[np.ndarray, list[int]] | None:
        """The lag window's records of ``observations`` (``rsu_imu_batch.batch_records``) when the last
        batch this thread processed was read from that very sequence; else None (the window's codec
        writes them from the observations). The lag window asks right after ``process``."""
        last = getattr(_LAST_READ, "batch", None)
        if last is None or last[0] is not observations:
            return None
        return batch_records(last[1])

    smoother: ClassVar[bool] = True

    def smooth(
        self,
        state: bytes,
        observations: Sequence[Observation],
        environment: Environment,
        lag_s: float | None = None,
    ) -> list[Fix]:
        """Filter ``observations`` from ``state`` exactly as process() does (same validation, same fixes'
        t/status/measurements), recording what the backward pass needs, then smooth backwards: one
        smoothed fix per epoch, in time order. lag_s None: fixed-interval (every epoch smoothed with all
        the given data). lag_s = L: fixed-lag, each epoch's estimate uses only the data up to t + L (what
        a live track with a window of L seconds shows for its oldest point).

        Kim's IMM smoother (``core.smoothing``); segments and recording: ``pipelines.rsu_imu_smoothing``.
        The returned state of the forward pass is not kept: smoothing never advances a session."""
        from edgepos.pipelines import rsu_imu_smoothing  # it builds on this module's helpers

        return rsu_imu_smoothing.smooth(state, observations, environment, lag_s)


# -- the bank ------------------------------------------------------------------------------------
def _options_key(options: Mapping[str, Any]) -> str:
    return json.dumps(options, sort_keys=True)


def _models(options: Mapping[str, Any]) -> list[MotionModel]:
    return [make_motion_model(name, **options["model_params"].get(name, {})) for name in options["models"]]


def _filter(options: Mapping[str, Any], models: Sequence[MotionModel]) -> GaussianFilter:
    """The configured filter, checked against every model's dimension (a UKF spread can be invalid)."""
    filt = make_filter(options["filter"], **options["filter_params"])
    if isinstance(filt, SigmaPointFilter):
        for model in models:
            filt.point_weights(model.dim)
    return filt


@functools.lru_cache(maxsize=128)
def _stepper(bank: InteractingMultipleModel) -> BankStepper:
    """The compiled stepper of a bank when the kernels cover it, else the numpy reference."""
    return stepper_for(bank)


@functools.lru_cache(maxsize=128)
def _bank(options_key: str) -> InteractingMultipleModel:
    options = json.loads(options_key)
    models = _models(options)
    filt = _filter(options, models)
    count = len(models)
    if options["transition"] is not None:
        transition = np.array(options["transition"], dtype=float)
    elif count == 1:
        transition = np.ones((1, 1))
    else:
        stay = options["transition_diagonal"]
        transition = np.full((count, count), (1.0 - stay) / (count - 1))
        np.fill_diagonal(transition, stay)
    priority = [options["models"].index(name) for name in options["priority"]] or None
    return InteractingMultipleModel(models, filt, transition, priority)


def _initial_probabilities(options: Mapping[str, Any], count: int) -> np.ndarray:
    if options["initial_probabilities"] is None:
        return np.full(count, 1.0 / count)
    return np.array(options["initial_probabilities"], dtype=float)


def _decode(blob: bytes) -> _SessionState:
    if blob[: len(_MAGIC)] != _MAGIC:
        return _decode_json(blob)
    try:
        _, version, flags, t, filter_t, epochs, count, key_length = _STATE.unpack_from(blob)
    except struct.error:
        raise state_format.StateFormatError("rsu_imu state is truncated") from None
    if version != _VERSION:
        raise state_format.StateFormatError(
            f"rsu_imu state version {version} is not {_VERSION}: open a new session"
        )
    start = _STATE.size + key_length
    size = count * _FLOATS_PER_MODEL
    end = start + 8 * size
    if not count or flags > _ALL_FLAGS or len(blob) < end:
        raise state_format.StateFormatError("rsu_imu state is truncated or corrupt")
    try:
        key = blob[_STATE.size : start].decode()
        options = _options_from_key(key)
    except (UnicodeDecodeError, TypeError, ValueError) as error:
        raise state_format.StateFormatError(f"rsu_imu state is corrupt: {error!r}") from None
    values = np.frombuffer(blob, dtype="<f8", count=size, offset=start).astype(float)  # one writable copy
    return _SessionState(
        options,
        bool(flags & _INITIALISED),
        t if flags & _HAS_T else None,
        filter_t if flags & _HAS_FILTER_T else None,
        epochs,
        values[:count],
        values[count : count * (1 + layout.FULL_DIM)].reshape(count, layout.FULL_DIM),
        values[count * (1 + layout.FULL_DIM) :].reshape(count, *_FULL_COV),
        key,
        bank_from_tail(blob[end:]),
    )


def _output(result: StepResult) -> Gaussian:
    return result.output


def _decode_json(blob: bytes) -> _SessionState:
    """A state in the layout before ``_STATE``: ``core.state``'s JSON header and named arrays (sessions
    stored before the upgrade go on; the next batch writes them in the binary layout)."""
    meta, arrays = state_format.unpack(blob)
    if meta.get("pipeline") != RsuImuPipeline.name:
        raise state_format.StateFormatError("state does not belong to the rsu_imu pipeline")
    try:
        key = meta.get("options_json")
        if isinstance(key, str):
            options = _options_from_key(key)
        else:  # written before the options were stored as their JSON text
            options = meta["options"]
            key = _options_key(options)
        return _SessionState(
            options,
            meta["initialised"],
            meta["t"],
            meta["filter_t"],
            meta["epochs"],
            arrays["probabilities"],
            arrays["means"],
            arrays["covs"],
            key,
        )
    except (KeyError, TypeError, ValueError) as error:
        raise state_format.StateFormatError(f"rsu_imu state is corrupt: {error!r}") from None


def _options_from_key(key: str) -> dict[str, Any]:
    """The options stored as ``key`` (their sorted JSON), parsed once per distinct text; a fresh
    top-level dict each time (the nested parameter dicts are shared and only ever read)."""
    options = _parsed_options(key)
    if not isinstance(options, dict):
        raise TypeError("the stored options are not a JSON object")
    return dict(options)


@functools.lru_cache(maxsize=256)
def _parsed_options(key: str) -> Any:
    return json.loads(key)


# -- one epoch -----------------------------------------------------------------------------------
def _step(
    session: _SessionState,
    bank: InteractingMultipleModel,
    parts: EpochParts,
    observations: Sequence[Observation],
    batch: Batch,
) -> Fix:
    options = session.options
    epoch = parts.indices
    t = observations[epoch[0]].t
    session.t = t
    session.epochs += 1
    uses, candidates, gyros = parts.uses, parts.candidates, parts.gyros

    if session.initialised and session.filter_t is not None and t - session.filter_t > options["max_gap"]:
        session.initialised = False  # too long without data: the old estimate says nothing any more
    if not session.initialised:
        if not candidates:
            for i in epoch:
                uses[i] = MeasurementUse(
                    i, observations[i].kind, False, "waiting for an RSU measurement to initialise"
                )
            return Fix(t=t, status="uninitialised", measurements=[uses[i] for i in sorted(uses)])
        _initialise(session, bank, candidates, gyros, observations, batch.rsus)
        session.integrity_bank = None
        for i in candidates + gyros:
            uses[i] = used(i, observations[i].kind)
        output = bank.combine(session.means, session.covs, session.probabilities)
        return epoch_fix(t, "initialised", output, session, bank, uses, nis=None, dof=0)

    dt = None if session.filter_t is None else t - session.filter_t
    stepper = _stepper(bank)
    measured = parts.measured
    gate = options["gate_probability"]
    gated = gate > 0.0 and bool(candidates or gyros)
    if options["integrity"] and _held_out(session.integrity_bank, t, candidates, observations):
        # the monitor leaves one of them out (monitored_update): the per-call path below
        prediction, fused = stepper.predict(session.means, session.covs, session.probabilities, dt), None
    else:  # in one compiled call when the gate keeps every measurement (fused None: it would not)
        thresholds = gate_thresholds(gate, bank.common) if gated else UNGATED
        prediction, fused = stepper.step(
            session.means, session.covs, session.probabilities, dt, measured, thresholds
        )
    if fused is None and gated:
        kept_rsus, kept_gyros = _gate(candidates, gyros, measured, prediction.output, gate, uses, stepper)
        if len(kept_rsus) < len(candidates) or len(kept_gyros) < len(gyros):
            candidates, gyros = kept_rsus, kept_gyros
            measured = epoch_measurements(candidates, gyros, batch, options)

    protection: Protection | None = None
    if options["integrity"]:
        result, candidates, measured, protection, session.integrity_bank = monitored_update(
            session.integrity_bank,
            t,
            candidates,
            measured,
            observations,
            options,
            uses,
            prediction.output,
            lambda kept: epoch_measurements(kept, gyros, batch, options),
            functools.partial(_correct, stepper, prediction, measured, fused),
            _output,
        )
    else:
        result = fused if fused is not None else stepper.correct(prediction, measured)
    for i in candidates + gyros:
        uses[i] = used(i, observations[i].kind)
    coasting = not (candidates or gyros)
    session.means, session.covs = result.means, result.covs
    session.probabilities = result.probabilities
    session.filter_t = t
    # ndarray.dot: the same BLAS dot product as @ (bit for bit) at a fifth of its cost on three numbers
    nis = None if coasting else float(result.probabilities.dot(result.nis))
    dof = 0 if coasting else measured.dim
    status = "predicted" if coasting else "tracking"
    return epoch_fix(t, status, result.output, session, bank, uses, nis, dof, protection)


def _correct(
    stepper: BankStepper,
    prediction: Prediction,
    measured: RsuGyroEpoch,
    fused: StepResult | None,
    epoch: RsuGyroEpoch,
) -> StepResult:
    """The correction of ``prediction`` with ``epoch``: ``fused``, the one compiled call's, when that
    corrected with these very measurements (``measured``), else the stepper's."""
    if fused is not None and epoch is measured:
        return fused
    return stepper.correct(prediction, epoch)


def _held_out(
    bank: SeparationBank | None, t: float, candidates: list[int], observations: Sequence[Observation]
) -> bool:
    """Whether the integrity monitor holds one of the RSU observations ``candidates`` out at ``t``
    (``SeparationBank.excluded_now``, which ``monitored_update`` asks again)."""
    if bank is None or not bank.excluded:
        return False
    held = bank.excluded_now(t)
    return any(cast(RsuObservation, observations[i]).rsu_id in held for i in candidates)


def _gate(
    candidates: list[int],
    gyros: list[int],
    measured: RsuGyroEpoch,
    prior: Gaussian,
    probability: float,
    uses: dict[int, MeasurementUse],
    stepper: BankStepper,
) -> tuple[list[int], list[int]]:
    """Mahalanobis gate of each RSU pair (2 dof) and gyro reading (1 dof) against the fused prior.

    ``measured`` holds the epoch's RSU pairs and gyros; each group's distance uses its own diagonal
    block of S = H P H^T + R, linearised at the prior mean. When most RSUs fail, the prediction is
    what is off (a lost track): the RSUs are all kept so that the filter can recover. A gyro is
    only gated when every model carries acceleration, since otherwise the bank has no yaw-rate
    prediction.
    """
    rsu_array, gyro_array = stepper.gate_distances(prior, measured)
    rsu_distance, gyro_distance = rsu_array.tolist(), gyro_array.tolist()  # a handful: cheaper as floats
    kept_rsus = candidates
    threshold = gate_threshold(probability, 2)
    failed = [distance > threshold for distance in rsu_distance]
    failures = sum(failed)
    if failures and failures * 2 <= len(candidates):
        kept_rsus = [i for i, bad in zip(candidates, failed) if not bad]
        for i, distance in zip(candidates, rsu_distance):
            if distance > threshold:
                uses[i] = MeasurementUse(
                    i, "rsu", False, f"failed the gate: d^2 = {distance:.1f} > {threshold:.1f}"
                )
    if not gyros or layout.XA not in prior.components or layout.YA not in prior.components:
        return kept_rsus, gyros
    threshold = gate_threshold(probability, 1)
    kept_gyros = []
    for i, distance in zip(gyros, gyro_distance):
        if distance > threshold:
            uses[i] = MeasurementUse(
                i, "gyro", False, f"failed the gate: d^2 = {distance:.1f} > {threshold:.1f}"
            )
        else:
            kept_gyros.append(i)
    return kept_rsus, kept_gyros


def _initialise(
    session: _SessionState,
    bank: InteractingMultipleModel,
    candidates: list[int],
    gyros: list[int],
    observations: Sequence[Observation],
    rsus: list[Rsu | None],
) -> None:
    """Start the filter from this epoch: position from the RSU fixes, velocity unknown."""
    options = session.options
    points, variances = [], []
    for i in candidates:  # RSU observations, whose stations read_batch found
        observation, rsu = cast(RsuObservation, observations[i]), cast(Rsu, rsus[i])
        points.append(
            [
                rsu.x + observation.range * math.cos(observation.bearing),
                rsu.y + observation.range * math.sin(observation.bearing),
            ]
        )
        range_std = rsu.range_std or options["range_std"]
        bearing_std = rsu.bearing_std or options["bearing_std"]
        variances.append(range_std**2 + (observation.range * bearing_std) ** 2)
    x, y = np.mean(points, axis=0)
    position_var = float(np.mean(variances)) / len(points)
    yaw_rate = (
        float(np.mean([cast(GyroObservation, observations[i]).yaw_rate for i in gyros])) if gyros else 0.0
    )
    velocity_var = options["init_velocity_std"] ** 2
    mean = np.array([x, 0.0, 0.0, y, 0.0, 0.0, 0.0, yaw_rate])
    variances8 = [
        position_var,
        velocity_var,
        _INITIAL_ACCEL_STD**2,
        position_var,
        velocity_var,
        _INITIAL_ACCEL_STD**2,
        _INITIAL_HEADING_STD**2,
        (options["gyro_std"] if gyros else _INITIAL_TURN_STD) ** 2,
    ]
    session.means, session.covs = bank.initial(mean, np.diag(variances8))
    session.initialised = True
    session.filter_t = observations[candidates[0]].t
