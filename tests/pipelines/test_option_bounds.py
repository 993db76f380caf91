"""Bounded options and finite fixes: every numeric option of every pipeline has a minimum and a maximum,
nested model and filter parameters are refused naming the exact field, and no pipeline returns a fix
holding NaN or infinity (the batch fails with NumericalError instead, which the service answers with
422 estimation_failed and the session unchanged)."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest
from edgepos.core.errors import NumericalError
from edgepos.core.observations import GnssFixObservation, GyroObservation
from edgepos.pipelines import rsu_imu, v2v_coop, v2x_federated
from edgepos.pipelines.base import (
    Fix,
    InitialState,
    PipelineInputError,
    StaticEnvironment,
    ensure_finite_fixes,
)
from edgepos.pipelines.registry import PIPELINES
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs

NUMERIC = ("number", "integer", "number[]", "matrix")


@functools.lru_cache(maxsize=1)
def scenario():
    return rsu_imu_paper_scenario()


def batch_observations(first: int, count: int) -> list:
    """Observations of the paper scenario's epochs first .. first+count-1."""
    epochs = rsu_imu_epochs(scenario(), np.random.default_rng(7))
    return [o for epoch in list(epochs)[first : first + count] for o in epoch]


@pytest.mark.parametrize("name", sorted(PIPELINES))
def test_every_numeric_option_has_both_bounds(name: str) -> None:
    unbounded = [
        spec.name
        for spec in PIPELINES[name].option_specs()
        if spec.type in NUMERIC and (spec.minimum is None or spec.maximum is None)
    ]
    assert unbounded == []


def _fields(pipeline: str, options: dict) -> list[str]:
    with pytest.raises(PipelineInputError) as caught:
        PIPELINES[pipeline].resolve_options(options)
    return [p.field for p in caught.value.problems]


@pytest.mark.parametrize(
    ("pipeline", "options", "field"),
    [
        # the 500s: accepted, then their squares overflowed on the first batch
        ("v2x_federated", {"gyro_std": 1e200}, "options.gyro_std"),
        ("v2x_federated", {"range_std": 1e308}, "options.range_std"),
        ("v2x_federated", {"odometer_std": 1e308}, "options.odometer_std"),
        ("v2v_coop", {"gps_std": 1e200}, "options.gps_std"),
        ("v2v_coop", {"max_neighbour_age": 1e300}, "options.max_neighbour_age"),
        ("rsu_imu", {"model_params": {"singer": {"sigma": 1e200}}}, "options.model_params.singer.sigma"),
        # nested parameters: unknown names, wrong types and out-of-range values, by their exact field
        ("rsu_imu", {"model_params": {"at": {"bogus": 1.0}}}, "options.model_params.at.bogus"),
        ("rsu_imu", {"model_params": {"singer": {"alpha": "fast"}}}, "options.model_params.singer.alpha"),
        ("rsu_imu", {"model_params": {"singer": {"alpha": True}}}, "options.model_params.singer.alpha"),
        ("rsu_imu", {"model_params": {"ca": {"noise": "pink"}}}, "options.model_params.ca.noise"),
        (
            "rsu_imu",
            {"models": ["ca", "ct"], "priority": [], "model_params": {"ct": {"omega": 100.0}}},
            "options.model_params.ct.omega",
        ),
        ("rsu_imu", {"filter": "ukf", "filter_params": {"alpha": 50.0}}, "options.filter_params.alpha"),
        ("rsu_imu", {"filter_params": {"alpha": 0.5}}, "options.filter_params.alpha"),  # the CKF has none
        # list elements within the published bounds
        (
            "rsu_imu",
            {"transition": [[2.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]},
            "options.transition",
        ),
        ("rsu_imu", {"initial_probabilities": [1e300, 0.0, 0.0]}, "options.initial_probabilities"),
        # no models and no initial probabilities: the minimum of an empty list was a 500
        ("rsu_imu", {"models": [], "initial_probabilities": []}, "options.models"),
    ],
)
def test_out_of_bounds_values_are_refused_by_field(pipeline: str, options: dict, field: str) -> None:
    assert field in _fields(pipeline, options)


def test_every_bad_model_parameter_is_reported_at_once() -> None:
    options = {
        "models": ["ca", "singer"],
        "priority": [],
        "model_params": {"ca": {"q": 1e9}, "singer": {"sigma": 0.0}},
        "filter": "ukf",
        "filter_params": {"beta": -1.0},
    }
    assert set(_fields("rsu_imu", options)) == {
        "options.model_params.ca.q",
        "options.model_params.singer.sigma",
        "options.filter_params.beta",
    }


def test_the_option_descriptions_list_the_nested_bounds() -> None:
    specs = {spec.name: spec for spec in PIPELINES["rsu_imu"].option_specs()}
    assert "sigma (acceleration std, m/s^2; 0.0001..100)" in specs["model_params"].description
    assert "alpha (sigma-point spread; 0.001..1)" in specs["filter_params"].description


def test_ensure_finite_fixes_names_the_epoch_and_the_field() -> None:
    good = Fix(
        t=1.0, status="tracking", x=1.0, y=2.0, state=[1e308, 1e308], state_cov=[[1.0, 0.0], [0.0, 1.0]]
    )
    assert ensure_finite_fixes([good]) == [good]  # a sum that overflows is not a non-finite entry
    for field, value in (
        ("x", math.nan),
        ("yaw_rate", math.inf),
        ("state_cov", [[1.0, math.nan], [0.0, 1.0]]),
        ("position_cov", [[1.0, 0.0], [-math.inf, 1.0]]),
        ("kinematic_cov", [[1.0, 0.0], [0.0, math.nan]]),
    ):
        bad = dataclasses.replace(good, t=2.5, **{field: value})
        with pytest.raises(NumericalError, match=rf"t=2\.5 has a non-finite {field}"):
            ensure_finite_fixes([good, bad])


def _rsu_environment() -> StaticEnvironment:
    return StaticEnvironment(rsus={rsu.id: rsu for rsu in scenario().rsus})


def test_six_model_bank_with_a_loose_start_answers_finite_fixes() -> None:
    """The issue's NaN yaw rate: with every model and a 1e4 m initial position std, the turn-rate models'
    probabilities underflow to exactly 0, and their probability-weighted omega was 0/0. Now the yaw rate
    is unknown (None) while no model carrying it has probability, and every fix is finite."""
    pipeline = rsu_imu.RsuImuPipeline()  # unwrapped: the registry's plausibility check would restart it
    models = ["cv", "ca", "ct", "at", "singer", "current_statistical"]
    options = pipeline.resolve_options({"models": models, "priority": []})
    state = pipeline.create(options, InitialState(0.0, 0.0, 0.0, 0.0, position_std=1e4, velocity_std=1.0))
    fixes, _ = pipeline.process(state, batch_observations(0, 5), _rsu_environment())
    assert ensure_finite_fixes(fixes) == fixes
    assert fixes[1].yaw_rate is None  # ct's and at's probabilities are exactly 0 here
    assert fixes[1].model_probabilities["ct"] == fixes[1].model_probabilities["at"] == 0.0
    assert all(fix.yaw_rate is not None and math.isfinite(fix.yaw_rate) for fix in fixes[2:])


@pytest.mark.parametrize(
    ("module", "builder", "pipeline", "observations"),
    [
        (rsu_imu, "epoch_fix", "rsu_imu", lambda: batch_observations(0, 2)),
        (
            v2x_federated,
            "kinematic_fix",
            "v2x_federated",
            lambda: [
                GnssFixObservation(0.0, 0.0, 0.0),
                GnssFixObservation(0.2, 2.0, 0.0),
                GyroObservation(0.2, 0.0),
            ],
        ),
        (
            v2v_coop,
            "kinematic_fix",
            "v2v_coop",
            lambda: [GnssFixObservation(0.0, 0.0, 0.0), GnssFixObservation(0.2, 2.0, 0.0)],
        ),
    ],
)
def test_a_non_finite_fix_fails_the_batch(monkeypatch, module, builder, pipeline, observations) -> None:
    """Whatever goes non-finite inside, the pipeline raises NumericalError rather than return it."""
    original = getattr(module, builder)

    def poisoned(*args, **kwargs) -> Fix:
        return dataclasses.replace(original(*args, **kwargs), vx=math.nan)

    monkeypatch.setattr(module, builder, poisoned)
    runner = PIPELINES[pipeline]
    state = runner.create(runner.resolve_options({}), None)
    with pytest.raises(NumericalError, match="non-finite vx"):
        runner.process(state, observations(), _rsu_environment())


def test_unnormalisable_model_probabilities_raise() -> None:
    from edgepos.core.imm import _softmax

    assert np.allclose(_softmax(np.array([0.0, -1000.0])), [1.0, 0.0])
    for bad in ([np.nan, 0.0], [np.inf, 0.0], [-np.inf, -np.inf]):
        with pytest.raises(NumericalError):
            _softmax(np.array(bad))
