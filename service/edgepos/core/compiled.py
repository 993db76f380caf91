"""One IMM/2IMM epoch for RSU + gyro measurements: the numpy reference or the compiled kernels.

``BankStepper`` runs a bank (``core.imm``) on an ``RsuGyroEpoch`` with the readable numpy
reference. ``CompiledBankStepper`` runs the same equations through the numba kernels of
``core.kernels``, which agree with the reference to rounding (the tests check 1e-12 over every
filter, model set and option the kernels cover). :func:`stepper_for` picks the compiled one when
the bank is covered: an EKF, UKF or CKF over models that are linear with a fixed Q per interval
(CV, CA, CT, Singer) or the adaptive turn (AT). Anything else, and any step where the kernels meet
a Cholesky factor that does not exist or a non-finite number, runs on the numpy reference, which
repairs a nearly singular covariance or raises ``NumericalError``: the compiled path never decides
about bad numbers on its own. The models' F and Q for each interval are computed inside the prediction's
compiled call (``core.kernels_motion``), so timestamps that jitter, which make every interval new, stay
cheap. Each call writes its results into one array allocated per call; a compiled Prediction's arrays
are views of it, made when read (the gate and the correction take the array itself).
``CompiledBankStepper.step`` runs the usual epoch (prediction, gate, correction with every
measurement) in one compiled call (``core.kernels_epoch``) and leaves the rest to the calls above.

Set ``EDGEPOS_NUMBA=0`` to run everything on the numpy reference.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import time
from typing import Any, cast

import numpy as np

from edgepos.core import layout
from edgepos.core.filters import (
    CubatureKalmanFilter,
    ExtendedKalmanFilter,
    GaussianFilter,
    UnscentedKalmanFilter,
)
from edgepos.core.filters.sigma_points import SigmaPointFilter
from edgepos.core.imm import (
    Gaussian,
    InteractingMultipleModel,
    Prediction,
    StepResult,
    new_gaussian,
    new_step_result,
)
from edgepos.core.motion.at import AdaptiveTurn
from edgepos.core.motion.base import MotionModel, dt_key, padded_linear_step
from edgepos.core.motion.ca import ConstantAcceleration
from edgepos.core.motion.ct import CoordinatedTurn
from edgepos.core.motion.cv import ConstantVelocity
from edgepos.core.motion.singer import Singer
from edgepos.core.updates import RsuGyroEpoch, gate_distances

_log = logging.getLogger(__name__)


class BankStepper:
    """The numpy reference: a bank's prediction, correction and gate distances for one epoch."""

    compiled = False
    runs = False  # whether core.compiled_run steps a run of its epochs in one call

    def __init__(self, bank: InteractingMultipleModel) -> None:
        self.bank = bank

    def predict(
        self, means: np.ndarray, covs: np.ndarray, probabilities: np.ndarray, dt: float | None
    ) -> Prediction:
        """Interaction and every model's prediction over ``dt`` (none when dt is None or 0)."""
        return self.bank.predict(means, covs, probabilities, dt)

    def correct(self, prediction: Prediction, epoch: RsuGyroEpoch) -> StepResult:
        """Every model's update with ``epoch``, model probabilities and output; coasting without data."""
        correction = epoch.correction()
        if correction is None:
            return self.bank.coast(prediction)
        return self.bank.correct(prediction, correction)

    def gate_distances(self, prior: Gaussian, epoch: RsuGyroEpoch) -> tuple[np.ndarray, np.ndarray]:
        """Squared Mahalanobis distances of each RSU pair and gyro reading from ``prior``."""
        return gate_distances(prior, epoch)

    def step(
        self,
        means: np.ndarray,
        covs: np.ndarray,
        probabilities: np.ndarray,
        dt: float | None,
        epoch: RsuGyroEpoch,
        thresholds: tuple[float, float],
    ) -> tuple[Prediction, StepResult | None]:
        """The epoch's prediction and, where one call decides it, its correction with every measurement
        of ``epoch`` past the gate at ``thresholds``; here only the prediction (the caller gates and
        corrects: ``CompiledBankStepper.step`` does all three in one compiled call)."""
        return self.predict(means, covs, probabilities, dt), None


def _filter_kind(filt: GaussianFilter) -> int | None:
    from edgepos.core import kernels_base

    if type(filt) is ExtendedKalmanFilter:
        return kernels_base.EKF
    if type(filt) in (CubatureKalmanFilter, UnscentedKalmanFilter):
        return kernels_base.SIGMA
    return None


def _motion_kind(model: MotionModel) -> int | None:
    from edgepos.core import kernels_base

    if isinstance(model, AdaptiveTurn) and model.components == layout.ALL:
        return kernels_base.TURN
    if model.linear and not model.state_dependent_noise:
        return kernels_base.LINEAR
    return None


def _motion_row(model: MotionModel) -> tuple[int, list[float]]:
    """The kind and parameter row of ``model`` for ``kernels_motion.bank_step_matrices``, or UNCOVERED
    (a model it does not implement, a subclass included, whose F and Q come from the Python reference).
    The driving densities are computed as the models compute them."""
    from edgepos.core import kernels_motion as motion

    form = motion.CONTINUOUS if getattr(model, "noise", None) == "continuous" else motion.DISCRETE
    # type(model) is spelled out in each test so that the type checker narrows ``model`` to that class.
    if type(model) is ConstantVelocity:
        return motion.CV, [model.q, form, 0.0, 0.0]
    if type(model) is ConstantAcceleration:
        return motion.CA, [model.q, form, 0.0, 0.0]
    if type(model) is CoordinatedTurn:
        return motion.CT, [model.q, form, model.omega, 0.0]
    if type(model) is AdaptiveTurn and model.components == layout.ALL:
        return motion.AT, [model.q, form, model.beta, 2.0 * model.beta * model.eta * model.eta]
    if type(model) is Singer:
        return motion.SINGER, [model.alpha, 2.0 * model.alpha * model.sigma**2, 0.0, 0.0]
    return motion.UNCOVERED, [0.0] * motion.PARAMETER_COUNT


def _reference_step_matrices(models: tuple[MotionModel, ...], dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Padded F and Q of ``models`` as the compiled prediction takes them, from the Python closed forms:
    the linear ones' exact discretisation; for AT its turn-rate block F_omega (the kinematics follow
    the state's omega) and its Q."""
    transitions, noises = (np.array(m) for m in padded_linear_step(models, dt))
    zero = np.zeros(layout.FULL_DIM)
    for j, model in enumerate(models):
        if isinstance(model, AdaptiveTurn):
            transitions[j] = 0.0
            transitions[j][6:, 6:] = model.turn_rate_block(dt)[0]
            noises[j] = model.noise_covariance(zero, dt)
    return transitions, noises


def covered(bank: InteractingMultipleModel) -> bool:
    """Whether the compiled kernels implement this bank's filter and every one of its models."""
    return _filter_kind(bank.filter) is not None and all(_motion_kind(m) is not None for m in bank.models)


class CompiledBankStepper(BankStepper):
    """The same epoch through the numba kernels (see the module docstring)."""

    compiled = True

    def __init__(self, bank: InteractingMultipleModel) -> None:
        from edgepos.core import kernels, kernels_base

        filter_kind = _filter_kind(bank.filter)
        if filter_kind is None or not covered(bank):
            raise ValueError("the compiled kernels do not cover this bank")
        super().__init__(bank)
        self._kernels = kernels
        self._ok = kernels_base.OK
        count = len(bank.models)
        self._active = np.ascontiguousarray(bank.active)
        self._common = np.array(bank.common, dtype=np.int64)
        self._phi_slot = bank.common.index(layout.PHI) if layout.PHI in bank.common else -1
        self._transition = np.ascontiguousarray(bank.transition, dtype=float)
        self._priority = np.array(bank.priority if bank.is_two_stage else [], dtype=np.int64)
        self._others = np.array(bank.others, dtype=np.int64)
        self._kinds = np.array([_motion_kind(m) for m in bank.models], dtype=np.int64)
        from edgepos.core import kernels_motion

        self._motion_kernels = kernels_motion
        rows = [_motion_row(m) for m in bank.models]
        self._motion_kinds = np.array([kind for kind, _ in rows], dtype=np.int64)
        self._motion_params = np.array([row for _, row in rows], dtype=float).reshape(count, -1)
        self._uncovered = tuple(j for j, (kind, _) in enumerate(rows) if kind == kernels_motion.UNCOVERED)
        self._filter_kind = filter_kind
        weights = np.zeros((4, count))
        if isinstance(bank.filter, SigmaPointFilter):
            for j, model in enumerate(bank.models):
                weights[:, j] = bank.filter.point_weights(model.dim)
        self._weights = np.ascontiguousarray(weights)  # spreads, side, centre mean and cov weights
        self._has_centre = bool(getattr(bank.filter, "has_centre_point", False))
        self._sizes = (count, len(bank.common))
        self._prediction_size = kernels.prediction_size(*self._sizes)
        self._correction_size = kernels.correction_size(*self._sizes)
        from edgepos.core import kernels_epoch

        self._epoch_kernels = kernels_epoch
        self._epoch_size = self._prediction_size + self._correction_size
        self.runs = not self._uncovered

    @functools.lru_cache(maxsize=64)  # noqa: B019 (steppers live as long as their cached bank)
    def _step_matrices(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Padded F and Q of every model for an interval (see ``_reference_step_matrices``), in one
        compiled call (``core.kernels_motion``): a few microseconds, where the Python closed forms
        cost about 90 for a bank, and jittered timestamps make every interval new. Models the kernel
        does not cover take the Python reference's rows."""
        count = len(self.bank.models)
        transitions, noises = np.empty((count, 8, 8)), np.empty((count, 8, 8))
        self._motion_kernels.bank_step_matrices(
            self._motion_kinds, self._motion_params, dt, transitions, noises
        )
        if self._uncovered:
            models = tuple(self.bank.models[j] for j in self._uncovered)
            reference_transitions, reference_noises = _reference_step_matrices(models, dt)
            for row, j in enumerate(self._uncovered):
                transitions[j] = reference_transitions[row]
                noises[j] = reference_noises[row]
        return transitions, noises

    def predict(
        self, means: np.ndarray, covs: np.ndarray, probabilities: np.ndarray, dt: float | None
    ) -> Prediction:
        out = np.empty(self._prediction_size)  # fresh per call: the Prediction may outlive the next epoch
        means = np.ascontiguousarray(means, dtype=float)
        covs = np.ascontiguousarray(covs, dtype=float)
        probabilities = np.ascontiguousarray(probabilities, dtype=float)
        step_dt = dt_key(dt) if dt else 0.0  # the reference's rounding of dt for F and Q
        # both kernels start with the filters, the bank's mixing and the interval, and end with the filter's
        # weights and the output array; in between, F and Q or what computes them
        head = (
            means,
            covs,
            probabilities,
            self._transition,
            self._active,
            self._common,
            self._phi_slot,
            float(dt) if dt else 0.0,
        )
        tail = (self._filter_kind, self._weights, self._has_centre, out)
        if self._uncovered:  # F and Q from the Python closed forms for some model: passed in
            transitions, noises = self._step_matrices(step_dt)
            status = self._kernels.predict_step(*head, self._kinds, transitions, noises, *tail)
        else:  # F and Q in the same compiled call
            status = self._kernels.predict_epoch(
                *head, step_dt, self._motion_kinds, self._motion_params, self._kinds, *tail
            )
        if status != self._ok:
            return super().predict(means, covs, probabilities, dt)  # repairs, or raises NumericalError
        return _packed_prediction(out, self._sizes, self.bank.common)

    def step(
        self,
        means: np.ndarray,
        covs: np.ndarray,
        probabilities: np.ndarray,
        dt: float | None,
        epoch: RsuGyroEpoch,
        thresholds: tuple[float, float],
    ) -> tuple[Prediction, StepResult | None]:
        """The epoch in one compiled call when it can (``core.kernels_epoch``): the prediction, and the
        correction with every measurement of ``epoch`` when the gate at ``thresholds`` (RSU pairs, gyro
        readings; negative: not gated) would keep them all; else the correction is None and the caller gates and
        corrects on the per-call path. A failed prediction or correction is done on the numpy reference,
        as ``predict`` and ``correct`` do."""
        if self._uncovered or (epoch.rsu_count == 0 and epoch.yaw_rates.size == 0):
            return self.predict(means, covs, probabilities, dt), None
        positions, observed, yaw_rates, range_variances, bearing_variances, gyro_variance = (
            epoch.kernel_arrays
        )
        out = np.empty(self._epoch_size + positions.shape[0] + yaw_rates.shape[0])  # fresh per call
        means = np.ascontiguousarray(means, dtype=float)
        covs = np.ascontiguousarray(covs, dtype=float)
        probabilities = np.ascontiguousarray(probabilities, dtype=float)
        status = self._epoch_kernels.epoch_step(
            means,
            covs,
            probabilities,
            self._transition,
            self._active,
            self._common,
            self._phi_slot,
            float(dt) if dt else 0.0,
            dt_key(dt) if dt else 0.0,  # the reference's rounding of dt for F and Q
            self._motion_kinds,
            self._motion_params,
            self._kinds,
            self._priority,
            self._others,
            positions,
            observed,
            yaw_rates,
            range_variances,
            bearing_variances,
            gyro_variance,
            epoch.gyro_min_speed**2,
            bool(epoch.averaged),
            thresholds[0],
            thresholds[1],
            self._filter_kind,
            self._weights,
            self._has_centre,
            out,
        )
        if status == self._ok:
            prediction = _packed_prediction(out[: self._prediction_size], self._sizes, self.bank.common)
            return prediction, self._step_result(out[self._prediction_size :])
        if status == self._epoch_kernels.GATED:
            return _packed_prediction(out[: self._prediction_size], self._sizes, self.bank.common), None
        if status == self._epoch_kernels.CORRECTION_FAILED:
            prediction = _packed_prediction(out[: self._prediction_size], self._sizes, self.bank.common)
            return prediction, super().correct(prediction, epoch)  # repairs, or raises NumericalError
        return super().predict(means, covs, probabilities, dt), None  # repairs, or raises NumericalError

    def _packed(self, prediction: Prediction) -> np.ndarray:
        """``prediction`` as ``predict_step``'s output array (one the reference made is packed here)."""
        packed = getattr(prediction, "packed", None)
        if packed is not None:
            return cast(np.ndarray, packed)
        output = prediction.output
        return np.concatenate(
            [
                np.ravel(prediction.means),
                np.ravel(prediction.covs),
                np.ravel(prediction.predicted_probabilities),
                np.ravel(output.mean),
                np.ravel(output.cov),
            ]
        ).astype(float)

    def correct(self, prediction: Prediction, epoch: RsuGyroEpoch) -> StepResult:
        if epoch.rsu_count == 0 and epoch.yaw_rates.size == 0:
            return self.bank.coast(prediction)
        out = np.empty(self._correction_size)  # fresh per call, as in predict
        status = self._kernels.correct_step(
            self._packed(prediction),
            self._active,
            self._common,
            self._phi_slot,
            self._priority,
            self._others,
            *epoch.kernel_arrays,
            epoch.gyro_min_speed**2,
            bool(epoch.averaged),
            self._filter_kind,
            self._weights,
            self._has_centre,
            out,
        )
        if status != self._ok:
            return super().correct(prediction, epoch)  # repairs, or raises NumericalError
        return self._step_result(out)

    def _step_result(self, out: np.ndarray) -> StepResult:
        """The StepResult over ``correct_step``'s output array ``out`` (views of it)."""
        means, covs, probabilities, mean, cov = self._kernels.prediction_views(out, *self._sizes)
        tail = self._prediction_size
        count = self._sizes[0]
        return new_step_result(
            means,
            covs,
            probabilities,
            new_gaussian(self.bank.common, mean, cov),
            out[tail : tail + count],
            out[tail + count : tail + 2 * count],
        )

    def gate_distances(self, prior: Gaussian, epoch: RsuGyroEpoch) -> tuple[np.ndarray, np.ndarray]:
        rsu = np.empty(epoch.rsu_count)
        gyro = np.empty(epoch.yaw_rates.size)
        packed = getattr(prior, "packed", None)
        if packed is not None:  # the fused prior of a compiled prediction: read from its output array
            self._kernels.gate_prediction(
                packed,
                self._sizes[0],
                self._common,
                *epoch.kernel_arrays,
                epoch.gyro_min_speed**2,
                rsu,
                gyro,
            )
            return rsu, gyro
        mean = np.zeros(layout.FULL_DIM)
        mean[self._common] = prior.mean
        self._kernels.gate_distances(
            mean,
            np.ascontiguousarray(prior.cov),
            self._common,
            *epoch.kernel_arrays,
            epoch.gyro_min_speed**2,
            rsu,
            gyro,
        )
        return rsu, gyro


class _PackedGaussian(Gaussian):
    """The fused prior of a compiled prediction: its mean and covariance are views of the
    prediction's output array, made when first read (the gate and the correction read the array)."""

    packed: np.ndarray
    _sizes: tuple[int, int]

    @functools.cached_property
    def mean(self) -> np.ndarray:
        return self._views[3]

    @functools.cached_property
    def cov(self) -> np.ndarray:
        return self._views[4]

    @functools.cached_property
    def _views(self) -> tuple[np.ndarray, ...]:
        from edgepos.core.kernels import prediction_views

        return prediction_views(self.packed, *self._sizes)


class _PackedPrediction(Prediction):
    """A compiled prediction: its arrays are views of ``predict_step``'s output array ``packed``, made
    when first read. The pipeline's epoch reads none of them: the gate and the correction take the
    array itself (``CompiledBankStepper``), which saves five views an epoch."""

    packed: np.ndarray

    @functools.cached_property
    def means(self) -> np.ndarray:
        return cast(_PackedGaussian, self.output)._views[0]

    @functools.cached_property
    def covs(self) -> np.ndarray:
        return cast(_PackedGaussian, self.output)._views[1]

    @functools.cached_property
    def predicted_probabilities(self) -> np.ndarray:
        return cast(_PackedGaussian, self.output)._views[2]


def _packed_prediction(out: np.ndarray, sizes: tuple[int, int], common: tuple[int, ...]) -> Prediction:
    """A Prediction over ``predict_step``'s output array ``out``, its arrays made when first read."""
    output = object.__new__(_PackedGaussian)
    output.__dict__.update(components=common, packed=out, _sizes=sizes)
    prediction = object.__new__(_PackedPrediction)
    prediction.__dict__.update(output=output, packed=out)
    return prediction


def compiled_enabled() -> bool:
    """False when ``EDGEPOS_NUMBA=0`` asks for the numpy reference, or numba cannot be imported. Asked
    many times an epoch (about fifteen in a ``gnss_tight`` one): the answer is kept for the setting's
    value, so a call costs one environment read (a change of the variable, as tests make, is seen)."""
    global _enabled
    setting = os.environ.get("EDGEPOS_NUMBA", "1")
    last_setting, last_answer = _enabled
    if setting == last_setting:
        return last_answer
    enabled = setting.strip().lower() not in ("0", "false", "no", "off") and _numba_imports()
    _enabled = (setting, enabled)
    return enabled


_enabled: tuple[str | None, bool] = (None, False)  # the EDGEPOS_NUMBA value last answered for, its answer


def _numba_imports() -> bool:
    try:
        from edgepos.core import kernels  # noqa: F401  # imported only to learn whether numba imports
    except ImportError as error:  # pragma: no cover - numba is a dependency; this is a safety net
        _log.warning("numba unavailable (%s): filtering runs on the numpy reference", error)
        return False
    return True


def stepper_for(bank: InteractingMultipleModel) -> BankStepper:
    """The compiled stepper when it is enabled and covers ``bank``, else the numpy reference."""
    if compiled_enabled() and covered(bank):
        return CompiledBankStepper(bank)
    return BankStepper(bank)


_KERNEL_MODULES = (
    "kernels_base",
    "kernels",
    "kernels_correct",
    "kernels_motion",
    "kernels_turn",
    "kernels_integrity",
    "kernels_epoch",
    "kernels_run",
    "measurements.gnss_kernel",
    "measurements.gnss_geometry",
    "measurements.gnss_raim_kernel",
    "measurements.gnss_noise_kernel",
    "particles.upf_kernel",
    "particles.upf_step_kernel",
    "particles.upf_resample_kernel",
)


def _kernel_dispatchers() -> list[Any]:
    """Every numba dispatcher of the kernel modules (imported here: numba must import)."""
    import importlib

    from numba.core.dispatcher import Dispatcher

    found: dict[int, Any] = {}
    for name in _KERNEL_MODULES:
        module = importlib.import_module(f"edgepos.core.{name}")
        found.update({id(value): value for value in vars(module).values() if isinstance(value, Dispatcher)})
    return list(found.values())


def kernel_cache_dir() -> str | None:
    """Where numba keeps the compiled kernels between starts (NUMBA_CACHE_DIR, next to the sources or
    the user's cache directory); None when it found nowhere writable and compiles at every start."""
    cache = getattr(_kernel_dispatchers()[0], "_cache", None)
    return getattr(cache, "cache_path", None) if getattr(cache, "_cache_file", None) is not None else None


def kernels_cached() -> bool:
    """Whether numba's on-disk cache has an entry for every kernel, so that :func:`warm_up` loads them
    (about a second) instead of compiling them (tens of seconds: the first start on a machine, with a
    fresh cache directory or after an upgrade). Only a CPU or source change it cannot see here makes a
    cached kernel compile again; :func:`kernels_compiled` tells afterwards."""
    if not compiled_enabled():
        return True  # nothing to compile: the numpy reference runs
    for dispatcher in _kernel_dispatchers():
        cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
        if cache_file is None or not os.path.exists(cache_file._index_path):
            return False
    return True


def kernels_compiled() -> int:
    """Kernel signatures this process compiled rather than loaded from numba's cache (0 when numba's
    cache had them all, or when the kernels are off)."""
    if not compiled_enabled():
        return 0
    return sum(sum(dispatcher.stats.cache_misses.values()) for dispatcher in _kernel_dispatchers())


def warm_up() -> float:
    """Compile (or load from the on-disk cache) every kernel signature the service uses, so that no
    request pays it; returns the seconds it took. Runs one epoch of each covered filter kind, with
    the paper's 2IMM-CKF bank, joint and averaged, and the gate, the fused epoch
    (``core.kernels_epoch``) and a run of epochs (``core.kernels_run``); the predictions also compile the
    F and Q kernel (``core.kernels_motion``, one signature for every bank); then the integrity bank's
    kernels, gnss_tight's range kernel (``core.measurements.gnss_kernel``), its satellite geometry
    (``core.measurements.gnss_geometry``), RAIM and noise level
    (``core.measurements.gnss_raim_kernel``, ``gnss_noise_kernel``), the UPF's weights
    (``core.particles.upf_kernel``), its GNSS-only step (``core.particles.upf_step_kernel``) and its
    resampling (``core.particles.upf_resample_kernel``)."""
    started = time.perf_counter()
    if not compiled_enabled():
        return 0.0
    from edgepos.core.filters import make_filter
    from edgepos.core.motion import make_motion_model

    models = [make_motion_model(name) for name in ("ca", "at", "singer")]
    transition = np.full((3, 3), 0.01) + np.eye(3) * 0.97
    epoch = RsuGyroEpoch(
        positions=np.array([[0.0, -3.875], [50.0, 3.875]]),
        observed=np.array([[4.0, 1.4], [50.0, -3.0]]),
        range_std=np.array([0.6, 0.6]),
        bearing_std=np.array([0.01, 0.01]),
        yaw_rates=np.array([0.0]),
        gyro_std=0.005,
    )
    mean = np.array([0.5, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    for filter_name, priority in (("ckf", [0, 1]), ("ukf", None), ("ekf", None)):
        bank = InteractingMultipleModel(models, make_filter(filter_name), transition, priority)
        stepper = CompiledBankStepper(bank)
        means, covs = bank.initial(mean, np.eye(layout.FULL_DIM))
        prediction = stepper.predict(means, covs, np.full(3, 1.0 / 3.0), 0.05)
        stepper.gate_distances(prediction.output, epoch)
        for averaged in (False, True):
            stepper.correct(prediction, dataclasses.replace(epoch, averaged=averaged))
        stepper.step(means, covs, np.full(3, 1.0 / 3.0), 0.05, epoch, (5.99, 3.84))  # core.kernels_epoch
        if filter_name == "ckf":  # core.kernels_run: one signature serves every bank, monitored or not
            from edgepos.core.compiled_run import warm_up_run

            warm_up_run(stepper, epoch, means, covs)
    from edgepos.core import kernels_integrity

    kernels_integrity.warm_up()  # the integrity bank's kernels (core.integrity_bank)
    from edgepos.core.measurements import gnss_kernel

    gnss_kernel.warm_up()  # gnss_tight's pseudorange and range-rate kernel
    from edgepos.core.measurements import gnss_geometry

    gnss_geometry.warm_up()  # gnss_tight's satellite orbits and atmosphere
    from edgepos.core.measurements import gnss_raim_kernel

    gnss_raim_kernel.warm_up()  # gnss_tight's RAIM hypotheses
    from edgepos.core.measurements import gnss_noise_kernel

    gnss_noise_kernel.warm_up()  # gnss_tight's noise level fit
    from edgepos.core.particles import upf_kernel

    upf_kernel.warm_up()  # the UPF's importance weights
    from edgepos.core.particles import upf_step_kernel

    upf_step_kernel.warm_up()  # the UPF's time update, shared update and draws with the GNSS-only model
    from edgepos.core.particles import upf_resample_kernel

    upf_resample_kernel.warm_up()  # the UPF's regularised resampling
    return time.perf_counter() - started
