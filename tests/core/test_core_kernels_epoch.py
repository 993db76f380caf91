"""The one-call epoch (``core.kernels_epoch`` through ``CompiledBankStepper.step``) gives the per-call
path's prediction and correction bit for bit, hence the numpy reference's to rounding, and leaves to
the per-call path what it does not decide: a gate that would leave a measurement out, and a failed
prediction or correction (the numpy reference repairs or raises)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from edgepos.core import layout
from edgepos.core.compiled import BankStepper, CompiledBankStepper, compiled_enabled
from edgepos.core.errors import NumericalError
from edgepos.core.imm import Prediction, StepResult

from tests.core.test_core_compiled import (
    BANKS,
    DT,
    FILTERS,
    assert_same_prediction,
    assert_same_result,
    make_bank,
    make_epoch,
    random_bank_state,
)

pytestmark = pytest.mark.skipif(not compiled_enabled(), reason="the kernels are off (EDGEPOS_NUMBA=0)")

UNGATED = (-1.0, -1.0)


def assert_identical_prediction(got: Prediction, expected: Prediction) -> None:
    for name in ("means", "covs", "predicted_probabilities"):
        assert np.array_equal(getattr(got, name), getattr(expected, name)), name
    assert got.output.components == expected.output.components
    assert np.array_equal(got.output.mean, expected.output.mean)
    assert np.array_equal(got.output.cov, expected.output.cov)


def assert_identical_result(got: StepResult, expected: StepResult) -> None:
    for name in ("means", "covs", "probabilities", "log_likelihoods", "nis"):
        assert np.array_equal(getattr(got, name), getattr(expected, name)), name
    assert got.output.components == expected.output.components
    assert np.array_equal(got.output.mean, expected.output.mean)
    assert np.array_equal(got.output.cov, expected.output.cov)


@pytest.mark.parametrize("filter_name", FILTERS)
@pytest.mark.parametrize("bank_name", BANKS)
@pytest.mark.parametrize("averaged", [False, True], ids=["joint", "averaged"])
def test_one_call_equals_the_per_call_path_and_the_reference(
    filter_name: str, bank_name: str, averaged: bool
) -> None:
    rng = np.random.default_rng(hash(("epoch", filter_name, bank_name, averaged)) % 2**32)
    bank = make_bank(filter_name, bank_name)
    fast, slow = CompiledBankStepper(bank), BankStepper(bank)
    for rsus, gyros in ((4, 1), (1, 1), (3, 0), (2, 2), (0, 1)):
        means, covs, probabilities = random_bank_state(bank, rng)
        epoch = make_epoch(rng, rsus, gyros, averaged, means[0, [layout.XP, layout.YP]])
        prediction, result = fast.step(means, covs, probabilities, DT, epoch, UNGATED)
        assert result is not None
        per_call = fast.predict(means, covs, probabilities, DT)
        assert_identical_prediction(prediction, per_call)
        assert_identical_result(result, fast.correct(per_call, epoch))
        reference = slow.predict(means, covs, probabilities, DT)
        assert_same_prediction(prediction, reference)
        assert_same_result(result, slow.correct(reference, epoch))


def test_the_gate_decides_as_the_pipeline_does() -> None:
    """Thresholds placed between the per-call gate distances: one RSU of four beyond its threshold, or
    a gyro beyond its own, leave the epoch to the per-call path (the prediction given); every RSU
    beyond (the track lost: all kept), every distance within, or the gyros not gated, correct with
    every measurement."""
    rng = np.random.default_rng(21)
    bank = make_bank("ckf", "2imm-ca-at-singer")
    fast = CompiledBankStepper(bank)
    means, covs, probabilities = random_bank_state(bank, rng)
    epoch = make_epoch(rng, 4, 1, False, means[0, [layout.XP, layout.YP]])
    per_call = fast.predict(means, covs, probabilities, DT)
    corrected = fast.correct(per_call, epoch)
    rsu, gyro = fast.gate_distances(per_call.output, epoch)
    highest, lowest, gyro_distance = float(rsu.max()), float(rsu.min()), float(gyro[0])
    above = 2.0 * max(highest, gyro_distance)
    cases = {
        "all within": ((above, above), True),
        "one RSU beyond": ((math.nextafter(highest, 0.0), above), False),
        "every RSU beyond": ((0.5 * lowest, above), True),
        "the gyro beyond": ((above, math.nextafter(gyro_distance, 0.0)), False),
        "the gyro beyond, not gated": ((above, -1.0), True),
        "not gated": (UNGATED, True),
    }
    for name, (thresholds, decided) in cases.items():
        prediction, result = fast.step(means, covs, probabilities, DT, epoch, thresholds)
        assert_identical_prediction(prediction, per_call)
        assert (result is not None) == decided, name
        if result is not None:
            assert_identical_result(result, corrected)


def test_an_epoch_without_measurements_is_only_predicted() -> None:
    rng = np.random.default_rng(22)
    bank = make_bank("ckf", "2imm-ca-at-singer")
    fast = CompiledBankStepper(bank)
    means, covs, probabilities = random_bank_state(bank, rng)
    empty = make_epoch(rng, 0, 0, False, means[0, [0, 3]])
    prediction, result = fast.step(means, covs, probabilities, DT, empty, (5.99, 3.84))
    assert result is None
    assert_identical_prediction(prediction, fast.predict(means, covs, probabilities, DT))


def test_the_reference_stepper_only_predicts() -> None:
    rng = np.random.default_rng(23)
    bank = make_bank("ckf", "2imm-ca-at-singer")
    slow = BankStepper(bank)
    means, covs, probabilities = random_bank_state(bank, rng)
    epoch = make_epoch(rng, 4, 1, False, means[0, [0, 3]])
    prediction, result = slow.step(means, covs, probabilities, DT, epoch, UNGATED)
    assert result is None
    assert_identical_prediction(prediction, slow.predict(means, covs, probabilities, DT))


def test_a_prediction_the_kernels_refuse_is_repaired_by_the_reference() -> None:
    """A covariance whose plain Cholesky fails within rounding: the one call hands the prediction to the
    numpy reference, which repairs it, and leaves the correction to the caller."""
    bank = make_bank("ckf", "at")
    direction = np.ones(8) / math.sqrt(8.0)
    cov = np.outer(direction, direction) * 4.0 - 1e-15 * np.eye(8)
    means, covs = bank.initial(np.array([0.0, 9.0, 0.0, 0.0, 1.0, 0.0, 0.1, 0.0]), cov)
    epoch = make_epoch(np.random.default_rng(24), 2, 1, False, np.zeros(2))
    prediction, result = CompiledBankStepper(bank).step(means, covs, np.ones(1), DT, epoch, UNGATED)
    assert result is None
    expected = BankStepper(bank).predict(means, covs, np.ones(1), DT)
    assert np.array_equal(prediction.means, expected.means)
    assert np.array_equal(prediction.covs, expected.covs)


@pytest.mark.filterwarnings("ignore:invalid value encountered")
def test_bad_numbers_raise_the_typed_error() -> None:
    """A non-finite input to the prediction, or a non-finite measurement in the correction: the numpy
    reference raises, where the kernels only reported the failure."""
    rng = np.random.default_rng(25)
    bank = make_bank("ckf", "2imm-ca-at-singer")
    fast = CompiledBankStepper(bank)
    means, covs, probabilities = random_bank_state(bank, rng)
    epoch = make_epoch(rng, 4, 1, False, means[0, [0, 3]])
    broken = covs.copy()
    broken[1, 0, 0] = np.nan
    with pytest.raises(NumericalError):
        fast.step(means, broken, probabilities, DT, epoch, UNGATED)
    with pytest.raises(NumericalError):
        fast.step(
            means, covs, probabilities, DT, dataclasses.replace(epoch, yaw_rates=np.array([np.inf])), UNGATED
        )
