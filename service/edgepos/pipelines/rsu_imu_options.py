"""The ``rsu_imu`` pipeline's options: their specs (defaults, bounds, what each does) and the checks
across them and of the model and filter parameters, each problem named by its field."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from edgepos.core.errors import ConfigurationError
from edgepos.core.filters import FILTERS, make_filter
from edgepos.core.filters.sigma_points import SigmaPointFilter
from edgepos.core.motion import MOTION_MODELS, make_motion_model
from edgepos.pipelines.base import (
    OptionSpec,
    Problem,
)
from edgepos.pipelines.integrity import INTEGRITY_SPECS

#: Standard deviations of the components an initial state does not give (acceleration m/s^2,
#: heading rad, turn rate rad/s).


def parameters_text(owners: Mapping[str, Any]) -> str:
    """The settable parameters of each model or filter with their bounds, for the option descriptions."""
    return "; ".join(
        f"{name}: " + (", ".join(spec.describe() for spec in cls.parameters) or "none")
        for name, cls in owners.items()
    )


OPTION_SPECS: tuple[OptionSpec, ...] = (
    OptionSpec(
        "filter",
        "string",
        "ckf",
        "Filter inside every model: ekf, ukf, ckf or srukf.",
        choices=tuple(FILTERS),
    ),
    OptionSpec(
        "filter_params",
        "object",
        {},
        'Filter tuning, e.g. {"alpha": 1, "beta": 2, "kappa": null} for the UKF. Parameters by filter, '
        f"with their bounds: {parameters_text(FILTERS)}.",
    ),
    OptionSpec(
        "models",
        "string[]",
        ["ca", "at", "singer"],
        "Motion models of the bank, in order; one model means plain filtering.",
        choices=tuple(MOTION_MODELS),
    ),
    OptionSpec(
        "model_params",
        "object",
        {},
        'Per-model parameters by model name, e.g. {"ct": {"omega": 0.35}}; unset ones take the paper\'s values. '
        f"Parameters by model, with their bounds: {parameters_text(MOTION_MODELS)}.",
    ),
    OptionSpec(
        "priority",
        "string[]",
        ["ca", "at"],
        "2IMM priority set (eqs. 29-38): models that interact first. Empty or all models: plain IMM.",
        choices=tuple(MOTION_MODELS),
    ),
    OptionSpec(
        "transition_diagonal",
        "number",
        0.98,
        "Probability of staying in a model per epoch; the rest is shared equally by the others.",
        minimum=0.0,
        maximum=1.0,
    ),
    OptionSpec(
        "transition",
        "matrix",
        None,
        "Full model transition matrix, row i = from model i (rows sum to 1); overrides transition_diagonal.",
        minimum=0.0,
        maximum=1.0,
    ),
    OptionSpec(
        "initial_probabilities",
        "number[]",
        None,
        "Initial model probabilities, one per model (sum 1); default uniform.",
        minimum=0.0,
        maximum=1.0,
    ),
    OptionSpec(
        "rsu_handling",
        "string",
        "joint",
        "joint: one update with every RSU stacked; average: one update per RSU, estimates averaged (the paper).",
        choices=("joint", "average"),
    ),
    OptionSpec(
        "max_rsus", "integer", 4, "Use at most this many RSUs per epoch, the nearest by range.", 1, 64
    ),
    OptionSpec(
        "comm_radius", "number", 160.0, "RSU communication radius (m) unless an RSU sets its own.", 1.0, 1e5
    ),
    OptionSpec("range_std", "number", 0.6, "RSU range noise std (m) unless an RSU sets its own.", 1e-4, 1e4),
    OptionSpec(
        "bearing_std",
        "number",
        math.radians(0.5),
        "RSU bearing noise std (rad) unless an RSU sets its own.",
        1e-6,
        math.pi,
    ),
    OptionSpec("gyro_std", "number", math.radians(0.3), "Gyro yaw-rate noise std (rad/s).", 1e-6, 10.0),
    OptionSpec(
        "gate_probability",
        "number",
        0.9999,
        "Mahalanobis gate: reject a measurement whose squared distance exceeds this chi-square quantile; 0 disables.",
        0.0,
        0.999999999,
    ),
    OptionSpec(
        "max_gap",
        "number",
        5.0,
        "Longest time (s) between epochs the filter predicts across; after a longer gap it starts again "
        "from the next RSU measurements.",
        0.01,
        86400.0,
    ),
    OptionSpec(
        "init_velocity_std",
        "number",
        15.0,
        "Velocity std (m/s) when the pipeline initialises itself from RSU measurements.",
        0.01,
        1000.0,
    ),
    *INTEGRITY_SPECS,
)


def cross_check(options: dict[str, Any]) -> list[Problem]:
    problems = []
    models = options["models"]
    if not models:
        problems.append(Problem(None, "options.models", "must name at least one motion model"))
    missing = [p for p in options["priority"] if p not in models]
    if missing:
        problems.append(Problem(None, "options.priority", f"{missing} are not in options.models"))
    unknown = [name for name in options["model_params"] if name not in models]
    if unknown:
        problems.append(Problem(None, "options.model_params", f"{unknown} are not in options.models"))
    count = len(models)
    if options["transition"] is not None:
        matrix = np.array(options["transition"], dtype=object)
        if matrix.shape != (count, count):
            problems.append(
                Problem(None, "options.transition", f"must be {count}x{count}, one row per model")
            )
        elif np.any(np.array(options["transition"]) < 0) or not np.allclose(
            np.sum(options["transition"], axis=1), 1.0, atol=1e-9
        ):
            problems.append(Problem(None, "options.transition", "rows must be non-negative and sum to 1"))
    initial = options["initial_probabilities"]
    if initial is not None and count:  # without models, options.models is the problem
        if len(initial) != count:
            problems.append(Problem(None, "options.initial_probabilities", f"must have {count} entries"))
        elif min(initial) < 0 or not math.isclose(sum(initial), 1.0, abs_tol=1e-9):
            problems.append(
                Problem(None, "options.initial_probabilities", "must be non-negative and sum to 1")
            )
    for name, params in options["model_params"].items():
        if not isinstance(params, dict):
            problems.append(Problem(None, f"options.model_params.{name}", "must be a JSON object"))
    return problems


def parameter_problems(options: dict[str, Any]) -> list[Problem]:
    """Every model and filter parameter the core refuses (unknown, wrong type, out of its bounds), named
    by its field: ``options.model_params.singer.sigma``, ``options.filter_params.alpha``."""
    problems = []
    models = []
    for name in options["models"]:
        try:
            models.append(make_motion_model(name, **options["model_params"].get(name, {})))
        except (ConfigurationError, ValueError, TypeError) as error:
            problems.append(Problem(None, parameter_field(f"options.model_params.{name}", error), str(error)))
    try:
        filt = make_filter(options["filter"], **options["filter_params"])
        if isinstance(filt, SigmaPointFilter):
            for model in models:
                filt.point_weights(model.dim)  # a UKF spread can be invalid for a model's dimension
    except (ConfigurationError, ValueError, TypeError) as error:
        problems.append(Problem(None, parameter_field("options.filter_params", error), str(error)))
    return problems


def parameter_field(prefix: str, error: Exception) -> str:
    parameter = getattr(error, "parameter", None)
    return prefix if parameter is None else f"{prefix}.{parameter}"
