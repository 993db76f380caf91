"""rsu_imu option validation: defaults, and every kind of bad option named in the error."""

from __future__ import annotations

import math

import pytest
from edgepos.pipelines.base import PipelineInputError
from edgepos.pipelines.registry import PIPELINES, get_pipeline


@pytest.fixture(scope="module")
def pipeline():
    return get_pipeline("rsu_imu")


def test_registry_lists_the_pipeline_and_refuses_unknown_names() -> None:
    assert "rsu_imu" in PIPELINES
    assert get_pipeline("rsu_imu").name == "rsu_imu"
    with pytest.raises(KeyError):
        get_pipeline("no_such_pipeline")


def test_defaults_are_the_papers_2imm_ckf(pipeline) -> None:
    resolved = pipeline.resolve_options(None)
    assert resolved == pipeline.resolve_options({})
    assert resolved["filter"] == "ckf"
    assert resolved["models"] == ["ca", "at", "singer"]
    assert resolved["priority"] == ["ca", "at"]
    assert resolved["max_rsus"] == 4 and resolved["comm_radius"] == 160.0
    assert resolved["range_std"] == 0.6
    assert resolved["bearing_std"] == pytest.approx(math.radians(0.5))
    assert resolved["gyro_std"] == pytest.approx(math.radians(0.3))
    assert set(resolved) == {spec.name for spec in pipeline.option_specs()}
    # resolving an effective configuration again changes nothing
    assert pipeline.resolve_options(resolved) == resolved


def test_resolving_does_not_alias_the_defaults(pipeline) -> None:
    first = pipeline.resolve_options(None)
    first["models"].append("cv")
    first["model_params"]["ca"] = {"q": 1.0}
    assert pipeline.resolve_options(None)["models"] == ["ca", "at", "singer"]
    assert pipeline.resolve_options(None)["model_params"] == {}


@pytest.mark.parametrize(
    "options",
    [
        {"filter": "ukf", "filter_params": {"alpha": 0.5, "beta": 2.0, "kappa": 0.0}},
        {"filter": "ekf", "models": ["cv", "ca", "ct", "singer"], "priority": ["cv", "ca"]},
        {"models": ["ca"], "priority": []},
        {"models": ["at"], "priority": ["at"]},
        {
            "models": ["ca", "at"],
            "priority": [],
            "transition": [[0.9, 0.1], [0.2, 0.8]],
            "initial_probabilities": [0.25, 0.75],
        },
        {"model_params": {"ct": {"omega": 0.35}}, "models": ["ca", "ct"], "priority": []},
        {"rsu_handling": "average", "max_rsus": 1, "gate_probability": 0.0},
        {"comm_radius": 1.0, "range_std": 1e-4, "bearing_std": math.pi, "gyro_std": 10, "max_rsus": 64},
        {"transition_diagonal": 0.0},
        {"transition_diagonal": 1},
    ],
)
def test_valid_options_are_accepted(pipeline, options: dict) -> None:
    resolved = pipeline.resolve_options(options)
    for name, value in options.items():
        assert resolved[name] == value


def problem_fields(error: PipelineInputError) -> list[str]:
    assert all(p.index is None for p in error.problems)
    return [p.field for p in error.problems]


BAD_OPTIONS = [
    # unknown option
    pytest.param({"filtre": "ckf"}, "filtre", id="unknown-option"),
    # wrong types
    pytest.param({"filter": 3}, "filter", id="filter-not-a-string"),
    pytest.param({"models": "ca"}, "models", id="models-not-a-list"),
    pytest.param({"models": ["ca", 1]}, "models", id="models-entry-not-a-string"),
    pytest.param({"max_rsus": 2.5}, "max_rsus", id="max-rsus-not-integer"),
    pytest.param({"max_rsus": True}, "max_rsus", id="max-rsus-bool"),
    pytest.param({"comm_radius": "160"}, "comm_radius", id="radius-string"),
    pytest.param({"range_std": float("nan")}, "range_std", id="range-std-nan"),
    pytest.param({"range_std": None}, "range_std", id="range-std-null"),
    pytest.param({"filter_params": [1]}, "filter_params", id="filter-params-not-object"),
    pytest.param({"transition": [[1.0, "x"]]}, "transition", id="transition-not-numbers"),
    pytest.param({"initial_probabilities": "uniform"}, "initial_probabilities", id="initial-not-list"),
    pytest.param({"rsu_handling": "sum"}, "rsu_handling", id="rsu-handling-choice"),
    # out of bounds
    pytest.param({"max_rsus": 0}, "max_rsus", id="max-rsus-zero"),
    pytest.param({"max_rsus": 65}, "max_rsus", id="max-rsus-too-many"),
    pytest.param({"comm_radius": 0.5}, "comm_radius", id="radius-too-small"),
    pytest.param({"range_std": 0.0}, "range_std", id="range-std-zero"),
    pytest.param({"bearing_std": -0.1}, "bearing_std", id="bearing-std-negative"),
    pytest.param({"gate_probability": 1.0}, "gate_probability", id="gate-one"),
    pytest.param({"transition_diagonal": 1.01}, "transition_diagonal", id="diagonal-above-one"),
    pytest.param({"init_velocity_std": 1e9}, "init_velocity_std", id="init-velocity-huge"),
    # names
    pytest.param({"models": ["ca", "zigzag"]}, "models", id="unknown-model"),
    pytest.param({"filter": "pf"}, "filter", id="unknown-filter"),
    pytest.param({"models": ["ca", "ca"], "priority": []}, "models", id="repeated-model"),
    # cross-field
    pytest.param({"priority": ["ca", "cv"]}, "priority", id="priority-not-in-models"),
    pytest.param({"models": ["ca"]}, "priority", id="default-priority-not-in-single-model"),
    pytest.param({"models": [], "priority": []}, "models", id="no-models"),
    pytest.param({"transition": [[0.5, 0.5], [0.5, 0.5]]}, "transition", id="transition-wrong-shape"),
    pytest.param(
        {"transition": [[1.0, 0.0, 0.0], [0.0, 1.0], [0.0, 0.0, 1.0]]}, "transition", id="transition-ragged"
    ),
    pytest.param(
        {"transition": [[0.5, 0.5, 0.5], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]},
        "transition",
        id="transition-row-sum",
    ),
    pytest.param(
        {"transition": [[1.5, -0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]},
        "transition",
        id="transition-negative",
    ),
    pytest.param({"initial_probabilities": [0.5, 0.5]}, "initial_probabilities", id="initial-wrong-length"),
    pytest.param({"initial_probabilities": [0.5, 0.6, -0.1]}, "initial_probabilities", id="initial-negative"),
    pytest.param({"initial_probabilities": [0.3, 0.3, 0.3]}, "initial_probabilities", id="initial-sum"),
    pytest.param({"model_params": {"cv": {"q": 1.0}}}, "model_params", id="params-for-absent-model"),
]


@pytest.mark.parametrize(("options", "field"), BAD_OPTIONS)
def test_bad_options_are_refused_naming_the_field(pipeline, options: dict, field: str) -> None:
    with pytest.raises(PipelineInputError) as caught:
        pipeline.resolve_options(options)
    fields = problem_fields(caught.value)
    assert any(f == f"options.{field}" or f.startswith(f"options.{field}.") for f in fields), fields
    assert all(p.reason for p in caught.value.problems)


@pytest.mark.parametrize(
    ("options", "field"),
    [
        pytest.param({"model_params": {"ca": {"q": -1.0}}}, "model_params", id="model-param-out-of-domain"),
        pytest.param({"model_params": {"at": {"bogus": 1.0}}}, "model_params", id="model-param-unknown-name"),
        pytest.param(
            {"model_params": {"singer": {"alpha": "fast"}}}, "model_params", id="model-param-wrong-type"
        ),
        pytest.param({"filter_params": {"gamma": 1.0}}, "filter_params", id="filter-param-unknown-for-ckf"),
        pytest.param(
            {"filter": "ukf", "filter_params": {"alpha": -1.0}}, "filter_params", id="ukf-alpha-negative"
        ),
        pytest.param(
            {"filter": "ukf", "filter_params": {"alpha": 1.0, "kappa": -20.0}},
            "filter_params",
            id="ukf-kappa-makes-spread-negative",
        ),
    ],
)
def test_bad_model_and_filter_parameters_are_pipeline_input_errors(
    pipeline, options: dict, field: str
) -> None:
    """resolve_options' contract: PipelineInputError naming the option, not a bare ConfigurationError
    escaping from building the bank (the service would have to guess which field was wrong)."""
    with pytest.raises(PipelineInputError) as caught:
        pipeline.resolve_options(options)
    assert any(
        f == f"options.{field}" or f.startswith(f"options.{field}.") for f in problem_fields(caught.value)
    )


def test_every_bad_option_is_reported_at_once(pipeline) -> None:
    with pytest.raises(PipelineInputError) as caught:
        pipeline.resolve_options({"bogus": 1, "max_rsus": 0, "filter": "pf", "range_std": -1.0})
    assert set(problem_fields(caught.value)) == {
        "options.bogus",
        "options.max_rsus",
        "options.filter",
        "options.range_std",
    }


def test_options_must_be_a_mapping(pipeline) -> None:
    with pytest.raises(PipelineInputError) as caught:
        pipeline.resolve_options(["filter", "ckf"])  # deliberately the wrong type
    assert problem_fields(caught.value) == ["options"]


def test_option_specs_document_every_option(pipeline) -> None:
    specs = pipeline.option_specs()
    names = [spec.name for spec in specs]
    assert len(names) == len(set(names))
    for spec in specs:
        assert spec.description
        if spec.minimum is not None and spec.maximum is not None:
            assert spec.minimum <= spec.maximum
