"""The compiled (numba) bank step equals the numpy reference to rounding, and hands every bad
number back to it.

Each case runs the same prediction, gate and correction through ``BankStepper`` (numpy reference)
and ``CompiledBankStepper`` (``core.kernels``) and compares every output: per-model means and
covariances, predicted and posterior model probabilities, log-likelihoods, NIS, the fused Gaussian
and the gate distances.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.compiled import BankStepper, CompiledBankStepper, covered, stepper_for, warm_up
from edgepos.core.errors import NumericalError
from edgepos.core.filters import CubatureKalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter
from edgepos.core.imm import Gaussian, InteractingMultipleModel, Prediction, StepResult
from edgepos.core.motion import make_motion_model
from edgepos.core.updates import RsuGyroEpoch, new_epoch

TOLERANCE = 1e-12
#: NIS and log-likelihoods go through S^-1; S mixes range variances (~0.4 m^2) with bearing ones
#: (~1e-5 rad^2), so its condition number (~1e4) amplifies rounding that much.
STATISTICS_TOLERANCE = 1e-10
DT = 0.05

FILTERS = {
    "ckf": CubatureKalmanFilter,
    "ukf": UnscentedKalmanFilter,
    "ukf-tuned": lambda: UnscentedKalmanFilter(alpha=0.5, beta=2.0, kappa=1.0),
    "ekf": ExtendedKalmanFilter,
}
#: (model names, 2IMM priority indices or None): the paper's banks, single models, unequal sets.
BANKS = {
    "2imm-ca-at-singer": (["ca", "at", "singer"], [0, 1]),
    "imm-ca-at-singer": (["ca", "at", "singer"], None),
    "2imm-singer-first": (["ca", "at", "singer"], [2]),
    "imm-cv-ct-at": (["cv", "ct", "at"], None),
    "2imm-cv-ca": (["cv", "ca"], [0]),
    "cv": (["cv"], None),
    "ca": (["ca"], None),
    "ct": (["ct"], None),
    "at": (["at"], None),
    "singer": (["singer"], None),
}


def make_bank(filter_name: str, bank_name: str, stay: float = 0.97) -> InteractingMultipleModel:
    names, priority = BANKS[bank_name]
    count = len(names)
    transition = np.ones((1, 1)) if count == 1 else np.full((count, count), (1 - stay) / (count - 1))
    if count > 1:
        np.fill_diagonal(transition, stay)
    return InteractingMultipleModel(
        [make_motion_model(n) for n in names], FILTERS[filter_name](), transition, priority
    )


def random_bank_state(bank: InteractingMultipleModel, rng: np.random.Generator):
    """Per-model Gaussians that differ from each other (so the interaction has work to do)."""
    count = len(bank.models)
    truth = np.array([30.0, 9.0, 0.4, 2.0, 1.5, -0.3, math.atan2(1.5, 9.0), 0.05])
    means, covs = [], []
    for _ in range(count):
        root = rng.standard_normal((8, 8)) * 0.15
        cov = root @ root.T + np.diag([0.3, 0.5, 0.4, 0.3, 0.5, 0.4, 0.02, 0.01])
        mean = truth + rng.standard_normal(8) * np.sqrt(np.diag(cov))
        mean[layout.PHI] = (mean[layout.PHI] + math.pi) % (2 * math.pi) - math.pi
        padded_means, padded_covs = bank.initial(mean, cov)
        means.append(padded_means[len(means)])
        covs.append(padded_covs[len(covs)])
    probabilities = rng.dirichlet(np.ones(count))
    return np.array(means), np.array(covs), probabilities


def make_epoch(rng, rsus: int, gyros: int, averaged: bool, near: np.ndarray) -> RsuGyroEpoch:
    positions = near[None, :] + rng.uniform(-60.0, 60.0, size=(rsus, 2))
    offsets = near[None, :] - positions + rng.standard_normal((rsus, 2)) * 0.5
    observed = np.column_stack(
        [np.hypot(offsets[:, 0], offsets[:, 1]), np.arctan2(offsets[:, 1], offsets[:, 0])]
    )
    return RsuGyroEpoch(
        positions=positions.reshape(rsus, 2),
        observed=observed.reshape(rsus, 2),
        range_std=rng.uniform(0.3, 1.0, rsus),
        bearing_std=rng.uniform(0.005, 0.02, rsus),
        yaw_rates=rng.normal(0.05, 0.01, gyros),
        gyro_std=math.radians(0.3),
        averaged=averaged,
    )


def assert_agree(
    actual, expected, what: str, scale: float | None = None, tolerance: float = TOLERANCE
) -> None:
    """Equal to rounding: within TOLERANCE relative to the array's scale (at least 1)."""
    expected = np.asarray(expected, dtype=float)
    actual = np.asarray(actual, dtype=float)
    assert actual.shape == expected.shape, what
    if scale is None:
        scale = max(1.0, float(np.max(np.abs(expected)))) if expected.size else 1.0
    difference = float(np.max(np.abs(actual - expected))) if expected.size else 0.0
    assert difference <= tolerance * scale, f"{what}: differs by {difference:.3g} (scale {scale:.3g})"


def assert_same_prediction(fast, slow) -> None:
    assert_agree(fast.means, slow.means, "predicted means")
    assert_agree(fast.covs, slow.covs, "predicted covariances")
    assert_agree(fast.predicted_probabilities, slow.predicted_probabilities, "predicted probabilities")
    assert fast.output.components == slow.output.components
    assert_agree(fast.output.mean, slow.output.mean, "fused prior mean")
    assert_agree(fast.output.cov, slow.output.cov, "fused prior covariance")


def assert_same_result(fast, slow) -> None:
    assert_agree(fast.means, slow.means, "posterior means")
    assert_agree(fast.covs, slow.covs, "posterior covariances")
    # Probabilities are exponentials of log-likelihood differences: a rounding-level relative
    # difference in a log-likelihood of size |l| moves them by about |l| times that.
    likelihood_scale = max(1.0, float(np.max(np.abs(slow.log_likelihoods))))
    assert_agree(
        fast.probabilities, slow.probabilities, "model probabilities", likelihood_scale, STATISTICS_TOLERANCE
    )
    assert_agree(
        fast.log_likelihoods, slow.log_likelihoods, "log-likelihoods", tolerance=STATISTICS_TOLERANCE
    )
    assert_agree(fast.nis, slow.nis, "NIS", tolerance=STATISTICS_TOLERANCE)
    assert fast.output.components == slow.output.components
    # The fused posterior is weighted by those probabilities, so it inherits their tolerance.
    assert_agree(fast.output.mean, slow.output.mean, "fused mean", tolerance=STATISTICS_TOLERANCE)
    assert_agree(fast.output.cov, slow.output.cov, "fused covariance", tolerance=STATISTICS_TOLERANCE)


def compare_epoch(bank, means, covs, probabilities, epoch, dt=DT):
    slow, fast = BankStepper(bank), CompiledBankStepper(bank)
    prediction = slow.predict(means, covs, probabilities, dt)
    fast_prediction = fast.predict(means, covs, probabilities, dt)
    if epoch.rsu_count or epoch.yaw_rates.size:
        rsu_slow, gyro_slow = slow.gate_distances(prediction.output, epoch)
        # the compiled stepper gates the reference's prior and its own (read from its output array)
        for prior in (prediction.output, fast_prediction.output):
            rsu_fast, gyro_fast = fast.gate_distances(prior, epoch)
            assert_agree(rsu_fast, rsu_slow, "RSU gate distances")
            assert_agree(gyro_fast, gyro_slow, "gyro gate distances")
    assert_same_prediction(fast_prediction, prediction)  # after the gate: its arrays made when read
    expected = slow.correct(prediction, epoch)
    assert_same_result(fast.correct(fast_prediction, epoch), expected)
    result = fast.correct(prediction, epoch)
    assert_same_result(result, expected)
    return result


def test_compiled_prediction_reads_the_same_from_its_array_as_a_plain_one() -> None:
    """A compiled prediction's gate and correction read its output array; the same numbers handed over
    as a plain Prediction (as after a fallback to the reference) give bit-identical answers, and the
    objects built without the dataclasses' __init__ equal those built with it."""
    rng = np.random.default_rng(3)
    bank = make_bank("ckf", "2imm-ca-at-singer")
    fast = CompiledBankStepper(bank)
    means, covs, probabilities = random_bank_state(bank, rng)
    epoch = make_epoch(rng, 3, 1, False, means[0, [layout.XP, layout.YP]])
    packed = fast.predict(means, covs, probabilities, DT)
    output = packed.output
    plain = Prediction(
        packed.means.copy(),
        packed.covs.copy(),
        packed.predicted_probabilities.copy(),
        Gaussian(output.components, output.mean.copy(), output.cov.copy()),
    )
    for got, expected in zip(
        fast.gate_distances(packed.output, epoch), fast.gate_distances(plain.output, epoch)
    ):
        assert np.array_equal(got, expected)
    result, expected = fast.correct(packed, epoch), fast.correct(plain, epoch)
    assert type(result) is StepResult and type(result.output) is Gaussian
    for name in ("means", "covs", "probabilities", "log_likelihoods", "nis"):
        assert np.array_equal(getattr(result, name), getattr(expected, name)), name
    assert np.array_equal(result.output.mean, expected.output.mean)
    assert np.array_equal(result.output.cov, expected.output.cov)
    rebuilt = StepResult(
        result.means,
        result.covs,
        result.probabilities,
        Gaussian(result.output.components, result.output.mean, result.output.cov),
        result.log_likelihoods,
        result.nis,
    )
    assert vars(rebuilt).keys() == vars(result).keys() and vars(rebuilt.output) == vars(result.output)
    assert all(getattr(rebuilt, k) is getattr(result, k) for k in vars(result) if k != "output")


@pytest.mark.parametrize("filter_name", FILTERS)
@pytest.mark.parametrize("bank_name", BANKS)
@pytest.mark.parametrize("averaged", [False, True], ids=["joint", "averaged"])
def test_compiled_epoch_equals_the_numpy_reference(filter_name: str, bank_name: str, averaged: bool) -> None:
    rng = np.random.default_rng(hash((filter_name, bank_name, averaged)) % 2**32)
    bank = make_bank(filter_name, bank_name)
    assert covered(bank)
    for rsus, gyros in ((4, 1), (1, 1), (3, 0), (2, 2), (0, 1)):
        means, covs, probabilities = random_bank_state(bank, rng)
        near = means[0, [layout.XP, layout.YP]]
        compare_epoch(bank, means, covs, probabilities, make_epoch(rng, rsus, gyros, averaged, near))


@pytest.mark.parametrize("filter_name", FILTERS)
def test_compiled_sequence_follows_the_reference_over_many_epochs(filter_name: str) -> None:
    """Each stepper runs on its own output for 60 epochs; they stay together to rounding."""
    rng = np.random.default_rng(5)
    bank = make_bank(filter_name, "2imm-ca-at-singer")
    slow, fast = BankStepper(bank), CompiledBankStepper(bank)
    means, covs, probabilities = random_bank_state(bank, rng)
    state_slow = state_fast = (means, covs, probabilities)
    position = np.array([30.0, 2.0])
    for _ in range(60):
        position = position + np.array([9.0, 1.5]) * DT
        epoch = make_epoch(rng, 4, 1, False, position)
        expected = slow.correct(slow.predict(*state_slow, DT), epoch)
        result = fast.correct(fast.predict(*state_fast, DT), epoch)
        assert_same_result(result, expected)
        state_slow = (expected.means, expected.covs, expected.probabilities)
        state_fast = (result.means, result.covs, result.probabilities)


def test_bearings_across_plus_minus_pi_agree() -> None:
    """The vehicle due west of an RSU: its sigma points' bearings straddle +-pi."""
    bank = make_bank("ckf", "2imm-ca-at-singer")
    rng = np.random.default_rng(11)
    means, covs, probabilities = random_bank_state(bank, rng)
    vehicle = means[0, [layout.XP, layout.YP]]
    for observed_bearing in (math.pi - 1e-4, -math.pi + 1e-4, -math.pi):
        for averaged in (False, True):
            positions = np.array([vehicle + [25.0, 0.0], vehicle + [40.0, 1e-3], vehicle + [-30.0, 5.0]])
            observed = np.array([[25.0, observed_bearing], [40.0, observed_bearing], [30.4, -0.16]])
            epoch = RsuGyroEpoch(
                positions,
                observed,
                np.full(3, 0.6),
                np.full(3, 0.01),
                np.array([0.05]),
                math.radians(0.3),
                averaged,
            )
            result = compare_epoch(bank, means, covs, probabilities, epoch)
            assert np.all(np.abs(result.output.mean[[0, 3]] - vehicle) < 5.0)


@pytest.mark.parametrize("filter_name", FILTERS)
def test_heading_near_plus_minus_pi_agrees(filter_name: str) -> None:
    """A heading at the wrap point: circular means in the turn prediction and the interaction."""
    bank = make_bank(filter_name, "imm-cv-ct-at")
    rng = np.random.default_rng(12)
    means, covs, probabilities = random_bank_state(bank, rng)
    means[:, layout.PHI] = np.where(bank.active[:, layout.PHI], math.pi - 0.01, 0.0)
    means[:, layout.XV] = -9.0
    epoch = make_epoch(rng, 4, 1, False, means[0, [layout.XP, layout.YP]])
    result = compare_epoch(bank, means, covs, probabilities, epoch)
    assert -math.pi <= result.means[2, layout.PHI] < math.pi


@pytest.mark.parametrize("dt", [0.0, None, 1e-10, 1e-6, 0.5, 3.0])
def test_other_intervals_agree(dt) -> None:
    bank = make_bank("ckf", "2imm-ca-at-singer")
    rng = np.random.default_rng(13)
    means, covs, probabilities = random_bank_state(bank, rng)
    compare_epoch(bank, means, covs, probabilities, make_epoch(rng, 4, 1, False, means[0, [0, 3]]), dt=dt)


def test_vanishing_model_probability_agrees() -> None:
    """No probability flows into a model (identity transition, zero prior): it keeps its own estimate."""
    names, priority = BANKS["imm-ca-at-singer"]
    bank = InteractingMultipleModel(
        [make_motion_model(n) for n in names], CubatureKalmanFilter(), np.eye(3), priority
    )
    rng = np.random.default_rng(14)
    means, covs, _ = random_bank_state(bank, rng)
    compare_epoch(
        bank, means, covs, np.array([0.5, 0.5, 0.0]), make_epoch(rng, 4, 1, False, means[0, [0, 3]])
    )


def test_nothing_measured_coasts_on_the_prediction() -> None:
    bank = make_bank("ckf", "2imm-ca-at-singer")
    rng = np.random.default_rng(15)
    means, covs, probabilities = random_bank_state(bank, rng)
    empty = make_epoch(rng, 0, 0, False, means[0, [0, 3]])
    fast = CompiledBankStepper(bank)
    prediction = fast.predict(means, covs, probabilities, DT)
    result = fast.correct(prediction, empty)
    assert result.means is prediction.means
    assert result.probabilities is prediction.predicted_probabilities
    assert np.all(np.isnan(result.nis))


def test_compiled_covariances_are_exactly_symmetric() -> None:
    bank = make_bank("ukf", "2imm-ca-at-singer")
    rng = np.random.default_rng(16)
    means, covs, probabilities = random_bank_state(bank, rng)
    fast = CompiledBankStepper(bank)
    prediction = fast.predict(means, covs, probabilities, DT)
    result = fast.correct(prediction, make_epoch(rng, 4, 1, False, means[0, [0, 3]]))
    for matrices in (prediction.covs, result.covs, prediction.output.cov[None], result.output.cov[None]):
        assert np.array_equal(matrices, matrices.transpose(0, 2, 1))
        assert np.all(np.linalg.eigvalsh(matrices) > 0.0) or matrices.shape[0] > 1


@pytest.mark.filterwarnings("ignore:invalid value encountered")
def test_non_finite_input_raises_the_typed_error() -> None:
    bank = make_bank("ckf", "2imm-ca-at-singer")
    rng = np.random.default_rng(17)
    means, covs, probabilities = random_bank_state(bank, rng)
    fast = CompiledBankStepper(bank)
    broken = covs.copy()
    broken[1, 0, 0] = np.nan
    with pytest.raises(NumericalError):
        fast.predict(means, broken, probabilities, DT)
    prediction = fast.predict(means, covs, probabilities, DT)
    epoch = make_epoch(rng, 4, 1, False, means[0, [0, 3]])
    with pytest.raises(NumericalError):
        fast.correct(prediction, dataclasses.replace(epoch, yaw_rates=np.array([np.inf])))


def test_indefinite_covariance_raises_the_typed_error() -> None:
    bank = make_bank("ckf", "at")
    means, covs = bank.initial(np.zeros(8), -np.eye(8))
    with pytest.raises(NumericalError):
        CompiledBankStepper(bank).predict(means, covs, np.ones(1), DT)


def test_nearly_singular_covariance_is_repaired_as_the_reference_does() -> None:
    """A covariance whose plain Cholesky fails within rounding: the kernels hand the step to the
    numpy reference, which repairs it; both give the same answer."""
    bank = make_bank("ckf", "at")
    direction = np.ones(8) / math.sqrt(8.0)
    cov = np.outer(direction, direction) * 4.0 - 1e-15 * np.eye(8)
    means, covs = bank.initial(np.array([0.0, 9.0, 0.0, 0.0, 1.0, 0.0, 0.1, 0.0]), cov)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(covs[0])
    slow = BankStepper(bank).predict(means, covs, np.ones(1), DT)
    fast = CompiledBankStepper(bank).predict(means, covs, np.ones(1), DT)
    assert np.array_equal(fast.means, slow.means) and np.array_equal(fast.covs, slow.covs)


def test_uncovered_banks_and_the_switch_use_the_numpy_reference(monkeypatch) -> None:
    paper = make_bank("ckf", "2imm-ca-at-singer")
    assert stepper_for(paper).compiled
    adaptive = InteractingMultipleModel(
        [make_motion_model("ca"), make_motion_model("current_statistical")],
        CubatureKalmanFilter(),
        np.array([[0.9, 0.1], [0.1, 0.9]]),
    )
    assert not covered(adaptive)
    assert not stepper_for(adaptive).compiled
    with pytest.raises(ValueError):
        CompiledBankStepper(adaptive)
    monkeypatch.setenv("EDGEPOS_NUMBA", "0")
    assert not stepper_for(paper).compiled
    assert warm_up() == 0.0


def test_warm_up_compiles_every_kernel_once() -> None:
    assert warm_up() >= 0.0
    assert warm_up() < 1.0  # the second time nothing is left to compile or load


def test_kernels_compile_in_memory_when_numba_has_nowhere_to_cache() -> None:
    """numba refuses cache=True for a function it cannot locate a writable cache for (here one
    without a source file); the kernels' decorator then compiles without a cache instead."""
    from edgepos.core import kernels, kernels_base

    namespace: dict = {}
    exec("def twice(x):\n    return 2.0 * x\n", namespace)  # noqa: S102 - a function without a source file is the point
    compiled = kernels_base._jit(namespace["twice"])
    assert compiled(2.5) == 5.0
    assert type(compiled._cache).__name__ == "NullCache"
    assert type(kernels.predict_step._cache).__name__ == "FunctionCache"  # the kernels themselves cache


def test_an_epoch_built_without_its_init_equals_one_built_with_it() -> None:
    """``updates.new_epoch`` (the rsu_imu pipeline's per-epoch constructor) gives the fields, variances
    and kernel arguments that ``RsuGyroEpoch(...)`` and its cached properties give."""
    rng = np.random.default_rng(8)
    made = make_epoch(rng, 3, 2, True, np.array([10.0, 0.0]))
    fast = new_epoch(
        made.positions,
        made.observed,
        made.range_std,
        made.bearing_std,
        made.yaw_rates,
        made.gyro_std,
        made.averaged,
        np.square(made.range_std),
        np.square(made.bearing_std),
    )
    assert type(fast) is RsuGyroEpoch
    for field in dataclasses.fields(RsuGyroEpoch):
        assert np.array_equal(getattr(fast, field.name), getattr(made, field.name)), field.name
    for name in ("variances", "kernel_arrays"):
        for got, expected in zip(getattr(fast, name), getattr(made, name), strict=True):
            assert np.array_equal(got, expected) and type(got) is type(expected), name
    assert fast.dim == made.dim
