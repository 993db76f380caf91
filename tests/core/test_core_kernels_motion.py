"""The compiled F and Q of a bank (``core.kernels_motion``) against the Python closed forms they
replace on the compiled path: every covered model, both noise forms, every parameter at its bounds,
intervals from 0.1 ms to the longest gap the rsu_imu pipeline predicts across; Q symmetric and
positive semi-definite; models the kernel does not cover keep the Python rows."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core import kernels_motion
from edgepos.core.compiled import CompiledBankStepper, _motion_row, _reference_step_matrices, warm_up
from edgepos.core.filters import CubatureKalmanFilter
from edgepos.core.imm import InteractingMultipleModel
from edgepos.core.motion import MOTION_MODELS, make_motion_model
from edgepos.core.motion.base import MotionModel, dt_key
from edgepos.core.motion.cv import ConstantVelocity
from edgepos.pipelines.rsu_imu_options import OPTION_SPECS
from hypothesis import example, given, settings
from hypothesis import strategies as st

COVERED = ("cv", "ca", "ct", "at", "singer")
#: The longest interval the pipeline predicts across (the upper bound of its ``max_gap`` option).
MAX_GAP = next(spec.maximum for spec in OPTION_SPECS if spec.name == "max_gap")
#: Intervals: 0 (the first prediction), 0.1 ms, the 20 Hz period with jitter, one where the Markov
#: series is summed without halving (rate T = 1/2 at the default Singer), long gaps that halve and
#: double the interval many times, and the pipeline's largest.
INTERVALS = (0.0, 1e-4, 0.048, 0.05, 0.0523456789, 0.625, 1.0, 5.0, 60.0, 823.98, 3600.0, 35881.8, MAX_GAP)
RELATIVE = 1e-13
#: Below the smallest normal float precision is absolute (4.9e-324 a step): a few thousand of those.
SUBNORMAL = 1e-320
#: F's entries exp(-rate T) of the Markov states (Singer's accelerations, AT's turn rate).
DECAYING = {"singer": ((2, 2), (5, 5)), "at": ((7, 7),)}


def transition_tolerance(model: MotionModel, dt: float) -> np.ndarray:
    """RELATIVE for every entry of F but the decaying ones of a Markov model: ``markov_chain`` squares
    exp(-rate h) once per doubling of the interval h, which doubles its relative rounding each time,
    in the reference as in the kernel (after ten doublings, about 2e-13 of a 7e-218, say)."""
    tolerance = np.full((8, 8), RELATIVE)
    rate = {"singer": getattr(model, "alpha", 0.0), "at": getattr(model, "beta", 0.0)}.get(model.name, 0.0)
    doublings = math.ceil(math.log2(rate * dt / 0.5)) if rate * dt > 0.5 else 0
    for entry in DECAYING.get(model.name, ()):
        tolerance[entry] = max(RELATIVE, 8.0 * np.finfo(float).eps * 2.0**doublings)
    return tolerance


def parameter_sets(name: str) -> list[dict]:
    """The model's defaults, each numeric parameter alone at its minimum and maximum, all at their
    minima and all at their maxima; each with every noise form the model has."""
    specs = MOTION_MODELS[name].parameters
    numeric = [spec for spec in specs if spec.choices is None]
    sets: list[dict] = [{}]
    for spec in numeric:
        sets += [{spec.name: spec.minimum}, {spec.name: spec.maximum}]
    sets += [{s.name: s.minimum for s in numeric}, {s.name: s.maximum for s in numeric}]
    forms = [spec for spec in specs if spec.choices is not None]
    if not forms:
        return sets
    (form,) = forms
    return [{**params, form.name: choice} for params in sets for choice in form.choices]


def kernel_rows(models: list[MotionModel], dt: float) -> tuple[np.ndarray, np.ndarray]:
    rows = [_motion_row(model) for model in models]
    kinds = np.array([kind for kind, _ in rows], dtype=np.int64)
    params = np.array([row for _, row in rows], dtype=float).reshape(len(models), -1)
    transitions = np.full((len(models), 8, 8), np.nan)  # the kernel must write every entry
    noises = np.full((len(models), 8, 8), np.nan)
    kernels_motion.bank_step_matrices(kinds, params, dt, transitions, noises)
    return transitions, noises


def assert_matches_reference(models: list[MotionModel], dt: float) -> None:
    """Every entry of every model's F and Q within RELATIVE of the reference's, and zero where it is."""
    transitions, noises = kernel_rows(models, dt)
    expected_transitions, expected_noises = _reference_step_matrices(tuple(models), dt)
    for j, model in enumerate(models):
        for what, actual, expected, tolerance in (
            ("F", transitions[j], expected_transitions[j], transition_tolerance(model, dt)),
            ("Q", noises[j], expected_noises[j], RELATIVE),
        ):
            label = f"{what} of {model.describe()} over {dt!r} s"
            np.testing.assert_array_equal(actual == 0.0, expected == 0.0, err_msg=f"{label}: zero pattern")
            bound = tolerance * np.abs(expected) + SUBNORMAL
            worst = np.unravel_index(np.argmax(np.abs(actual - expected) - bound), actual.shape)
            assert np.all(np.abs(actual - expected) <= bound), (
                f"{label}: {actual[worst]!r} != {expected[worst]!r} at {worst}"
            )


def assert_symmetric_positive_semidefinite(noise: np.ndarray, label: str) -> None:
    """Q exactly symmetric, and PSD as a correlation matrix (entries span dt^5 to dt, so the scaling
    keeps the eigenvalue test to rounding of order one numbers)."""
    np.testing.assert_array_equal(noise, noise.T, err_msg=label)
    used = np.nonzero(np.diag(noise))[0]
    assert np.all(noise[np.ix_(~np.isin(np.arange(8), used), np.arange(8))] == 0.0), label
    scale = 1.0 / np.sqrt(np.diag(noise)[used])
    correlation = noise[np.ix_(used, used)] * scale[:, None] * scale[None, :]
    assert np.min(np.linalg.eigvalsh(correlation)) >= -1e-12, label


def cases() -> list[tuple[str, dict]]:
    return [(name, params) for name in COVERED for params in parameter_sets(name)]


@pytest.mark.parametrize(("name", "params"), cases(), ids=lambda value: str(value))
def test_every_model_and_parameter_bound_matches_the_closed_forms(name: str, params: dict) -> None:
    model = make_motion_model(name, **params)
    assert _motion_row(model)[0] != kernels_motion.UNCOVERED
    for dt in INTERVALS:
        assert_matches_reference([model], dt_key(dt))
        noise = kernel_rows([model], dt_key(dt))[1][0]
        if dt > 0.0:
            assert_symmetric_positive_semidefinite(noise, f"Q of {model.describe()} over {dt} s")


def bounded(name: str, parameter: str) -> st.SearchStrategy[float]:
    """A parameter drawn log-uniformly between its bounds (uniformly, either sign, for omega)."""
    spec = next(spec for spec in MOTION_MODELS[name].parameters if spec.name == parameter)
    if spec.minimum <= 0.0:
        return st.floats(spec.minimum, spec.maximum)
    low, high = math.log(spec.minimum), math.log(spec.maximum)
    return st.floats(low, high).map(math.exp).map(lambda value: min(max(value, spec.minimum), spec.maximum))


@st.composite
def models(draw) -> MotionModel:
    name = draw(st.sampled_from(COVERED))
    params = {}
    for spec in MOTION_MODELS[name].parameters:
        params[spec.name] = draw(st.sampled_from(spec.choices) if spec.choices else bounded(name, spec.name))
    return make_motion_model(name, **params)


@settings(max_examples=300, deadline=None)
@given(
    bank=st.lists(models(), min_size=1, max_size=4),
    dt=st.floats(math.log(1e-4), math.log(MAX_GAP)).map(math.exp),
)
@example(bank=[make_motion_model("singer", alpha=100.0, sigma=100.0)], dt=MAX_GAP)
@example(bank=[make_motion_model("at", beta=100.0, eta=10.0, q=100.0, noise="continuous")], dt=6.9)
@example(bank=[make_motion_model("ct", omega=-2.0 * math.pi, noise="continuous")], dt=0.5)
@example(bank=[make_motion_model("ct", omega=0.0), make_motion_model("ct", omega=1e-12)], dt=0.05)
def test_random_banks_match_the_closed_forms(bank: list[MotionModel], dt: float) -> None:
    dt = dt_key(min(dt, MAX_GAP))
    assert_matches_reference(bank, dt)
    for model, noise in zip(bank, kernel_rows(bank, dt)[1]):
        assert_symmetric_positive_semidefinite(noise, f"Q of {model.describe()} over {dt} s")


class SlowConstantVelocity(ConstantVelocity):
    """A subclass the kernel does not know (it could override the closed forms): the Python rows."""


def test_stepper_takes_uncovered_models_from_the_python_reference() -> None:
    models = [SlowConstantVelocity(q=2.0), make_motion_model("at"), make_motion_model("singer", alpha=3.0)]
    assert [_motion_row(model)[0] for model in models] == [
        kernels_motion.UNCOVERED,
        kernels_motion.AT,
        kernels_motion.SINGER,
    ]
    transition = np.full((3, 3), 0.05) + np.eye(3) * 0.85
    stepper = CompiledBankStepper(InteractingMultipleModel(models, CubatureKalmanFilter(), transition))
    for dt in (0.05, dt_key(0.0512345), 7.5):
        transitions, noises = stepper._step_matrices(dt)
        expected_transitions, expected_noises = _reference_step_matrices(tuple(models), dt)
        np.testing.assert_array_equal(transitions[0], expected_transitions[0])
        np.testing.assert_array_equal(noises[0], expected_noises[0])
        np.testing.assert_allclose(transitions, expected_transitions, rtol=RELATIVE, atol=SUBNORMAL)
        np.testing.assert_allclose(noises, expected_noises, rtol=RELATIVE, atol=SUBNORMAL)
        assert transitions.flags.c_contiguous and noises.flags.c_contiguous


def test_warm_up_compiles_the_signature_the_stepper_calls_and_numba_caches_it_on_disk() -> None:
    warm_up()
    signatures = list(kernels_motion.bank_step_matrices.signatures)
    assert signatures
    models = [make_motion_model(name) for name in ("ca", "at", "singer")]
    transition = np.full((3, 3), 0.01) + np.eye(3) * 0.97
    stepper = CompiledBankStepper(
        InteractingMultipleModel(models, CubatureKalmanFilter(), transition, [0, 1])
    )
    stepper._step_matrices(dt_key(0.0498765))
    assert list(kernels_motion.bank_step_matrices.signatures) == signatures  # nothing new compiled
    assert type(kernels_motion.bank_step_matrices._cache).__name__ == "FunctionCache"
