"""Validation of pipeline options against their specs: types, bounds, choices, unknown names.

Types: "number", "integer", "boolean", "string", "string[]", "number[]", "matrix" (list of lists of
numbers) and "object" (a JSON object). A spec whose default is None accepts null. A spec's minimum and
maximum bound a number, or each element of a number[] or matrix.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

from edgepos.pipelines.base import OptionSpec, PipelineInputError, Problem, is_finite_number


def resolve_options(specs: Sequence[OptionSpec], options: Mapping[str, Any] | None) -> dict[str, Any]:
    """Defaults overlaid with ``options``; raises PipelineInputError listing every bad option."""
    by_name = {spec.name: spec for spec in specs}
    problems: list[Problem] = []
    resolved = {spec.name: copy.deepcopy(spec.default) for spec in specs}
    if options is not None and not isinstance(options, Mapping):
        raise PipelineInputError([Problem(None, "options", "must be a JSON object")])
    for name, value in (options or {}).items():
        spec = by_name.get(name)
        if spec is None:
            problems.append(
                Problem(None, f"options.{name}", f"unknown option; known: {', '.join(sorted(by_name))}")
            )
            continue
        reason = _check(spec, value)
        if reason:
            problems.append(Problem(None, f"options.{name}", reason))
        else:
            resolved[name] = (
                float(value) if spec.type == "number" and value is not None else copy.deepcopy(value)
            )
    if problems:
        raise PipelineInputError(problems)
    return resolved


def _check(spec: OptionSpec, value: Any) -> str | None:
    if value is None:
        return None if spec.default is None else "must not be null"
    kind = spec.type
    if kind == "number" or kind == "integer":
        if not is_finite_number(value) or (kind == "integer" and int(value) != value):
            return f"must be a finite {kind}"
        if spec.minimum is not None and value < spec.minimum:
            return f"must be >= {spec.minimum}"
        if spec.maximum is not None and value > spec.maximum:
            return f"must be <= {spec.maximum}"
    elif kind == "boolean":
        if not isinstance(value, bool):
            return "must be true or false"
    elif kind == "string":
        if not isinstance(value, str):
            return "must be a string"
    elif kind == "string[]":
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            return "must be a list of strings"
        if spec.choices is not None:
            unknown = [v for v in value if v not in spec.choices]
            if unknown:
                return f"unknown values {unknown}; choose from {list(spec.choices)}"
        if len(set(value)) != len(value):
            return "must not repeat a value"
        return None
    elif kind == "number[]":
        if not isinstance(value, list) or not all(is_finite_number(v) for v in value):
            return "must be a list of finite numbers"
        return _element_bounds(spec, value)
    elif kind == "matrix":
        if not isinstance(value, list) or not all(
            isinstance(row, list) and all(is_finite_number(v) for v in row) for row in value
        ):
            return "must be a list of rows of finite numbers"
        return _element_bounds(spec, [v for row in value for v in row])
    elif kind == "object" and not isinstance(value, dict):
        return "must be a JSON object"
    if spec.choices is not None and value not in spec.choices:
        return f"must be one of {list(spec.choices)}"
    return None


def _element_bounds(spec: OptionSpec, values: list[Any]) -> str | None:
    if spec.minimum is not None and any(v < spec.minimum for v in values):
        return f"every element must be >= {spec.minimum}"
    if spec.maximum is not None and any(v > spec.maximum for v in values):
        return f"every element must be <= {spec.maximum}"
    return None
