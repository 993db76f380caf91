"""The parameters a client may set on a motion model or a filter by name (the rsu_imu pipeline's
``model_params`` and ``filter_params``), with the bounds the service accepts.

The constructors only refuse values outside a parameter's mathematical domain (a non-positive noise,
say); these bounds are tighter, physically sensible ranges that also keep every square and product
the filters form finite with a wide margin (a noise std of 1e200 m/s^2 is positive, but its square
overflows). :func:`check_parameters` refuses an unknown name, a wrong type or a value outside its
range with a :class:`ConfigurationError` whose ``parameter`` names it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from edgepos.core.errors import ConfigurationError


@dataclass(frozen=True)
class ParameterSpec:
    """One settable parameter: a number in [minimum, maximum] (null allowed when ``nullable``), or
    one of ``choices``."""

    name: str
    description: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] | None = None
    nullable: bool = False

    @property
    def type(self) -> str:
        return "string" if self.choices is not None else "number"

    def describe(self) -> str:
        """``name`` with its range, for documentation: "sigma (m/s^2, 1e-4..100)"."""
        if self.choices is not None:
            allowed = " | ".join(self.choices)
        else:
            allowed = f"{self.minimum:g}..{self.maximum:g}" + (" or null" if self.nullable else "")
        return f"{self.name} ({self.description}; {allowed})"


def check_parameters(owner: str, specs: Sequence[ParameterSpec], params: Mapping[str, Any]) -> dict[str, Any]:
    """``params`` checked against ``specs``: returns them as plain floats/strings, or raises
    :class:`ConfigurationError` (``parameter`` = the offending name) for the first bad one."""
    by_name = {spec.name: spec for spec in specs}
    if not isinstance(params, Mapping):
        raise ConfigurationError(f"{owner} parameters must be a JSON object")
    checked: dict[str, Any] = {}
    for name, value in params.items():
        spec = by_name.get(name)
        if spec is None:
            known = ", ".join(sorted(by_name)) or "none"
            raise ConfigurationError(
                f"{owner} has no parameter {name!r}; known: {known}", parameter=str(name)
            )
        checked[name] = _check(owner, spec, value)
    return checked


def _check(owner: str, spec: ParameterSpec, value: Any) -> Any:
    if spec.choices is not None:
        if value not in spec.choices:
            raise ConfigurationError(
                f"{owner} {spec.name} must be one of {list(spec.choices)}", parameter=spec.name
            )
        return value
    if value is None and spec.nullable:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigurationError(f"{owner} {spec.name} must be a finite number", parameter=spec.name)
    if spec.minimum is not None and value < spec.minimum:
        raise ConfigurationError(f"{owner} {spec.name} must be >= {spec.minimum:g}", parameter=spec.name)
    if spec.maximum is not None and value > spec.maximum:
        raise ConfigurationError(f"{owner} {spec.name} must be <= {spec.maximum:g}", parameter=spec.name)
    return float(value)
