"""A pipeline that stands in for another and adds options of its own: the plausibility checks and the
lag window are both wrapped around every registered pipeline (``registry``).

The wrapper answers for the pipeline it wraps (its name, description, measurement kinds, smoother),
offers the inner options followed by its own, and resolves both together so that one error lists the
problems of either, with an unknown option told every name that is known.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from edgepos.pipelines.base import OptionSpec, Pipeline, PipelineInputError, Problem
from edgepos.pipelines.options import resolve_options


class WrappingPipeline(Pipeline):
    """``inner`` with ``own_specs`` options added; subclasses add what they do to its states and fixes."""

    own_specs: ClassVar[tuple[OptionSpec, ...]]

    def __init__(self, inner: Pipeline) -> None:
        if isinstance(inner, type(self)):
            raise TypeError(f"pipeline {inner.name!r} is already wrapped in {type(self).__name__}")
        self.inner = inner
        self._own_names = frozenset(spec.name for spec in self.own_specs)
        # Instance attributes over the ClassVars: the wrapper is the inner pipeline to its callers.
        self.name = inner.name  # type: ignore[misc]  # the wrapper answers for the pipeline it wraps
        self.description = inner.description  # type: ignore[misc]  # idem
        self.measurement_kinds = inner.measurement_kinds  # type: ignore[misc]  # idem
        self.publishes_track = inner.publishes_track  # type: ignore[misc]  # idem
        self.smoother = inner.smoother  # type: ignore[misc]  # idem

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.inner!r})"

    def option_specs(self) -> list[OptionSpec]:
        return [*self.inner.option_specs(), *self.own_specs]

    def inner_options(self, options: Mapping[str, Any]) -> dict[str, Any]:
        """The options that belong to the inner pipeline."""
        return {k: v for k, v in options.items() if k not in self._own_names}

    def resolve_options(self, options: Mapping[str, Any] | None) -> dict[str, Any]:
        """The inner pipeline's resolved options, then this wrapper's; problems of both in one error."""
        if options is not None and not isinstance(options, Mapping):
            raise PipelineInputError([Problem(None, "options", "must be a JSON object")])
        inner = None if options is None else self.inner_options(options)
        own = None if options is None else {k: v for k, v in options.items() if k in self._own_names}
        problems: list[Problem] = []
        resolved: dict[str, Any] = {}
        mine: dict[str, Any] = {}
        try:
            resolved = self.inner.resolve_options(inner)
        except PipelineInputError as error:
            problems.extend(self._with_all_names(error.problems))
        try:
            mine = resolve_options(self.own_specs, own)
        except PipelineInputError as error:
            problems.extend(error.problems)
        if problems:
            raise PipelineInputError(problems)
        return {**resolved, **mine}

    def _with_all_names(self, problems: Sequence[Problem]) -> list[Problem]:
        """The inner pipeline's "unknown option" problems list the wrapper's options as known too."""
        known = ", ".join(sorted({spec.name for spec in self.option_specs()}))
        return [
            dataclasses.replace(p, reason=f"unknown option; known: {known}")
            if p.reason.startswith("unknown option; known:")
            else p
            for p in problems
        ]
