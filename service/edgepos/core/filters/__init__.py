"""Filters and their registry: a new filter is one module plus one line here."""

from __future__ import annotations

from typing import Any

from edgepos.core.errors import ConfigurationError
from edgepos.core.filters.base import GaussianFilter, UpdateResult, kalman_correct
from edgepos.core.filters.ckf import CubatureKalmanFilter
from edgepos.core.filters.ekf import ExtendedKalmanFilter
from edgepos.core.filters.srukf import SquareRootUnscentedKalmanFilter
from edgepos.core.filters.ukf import UnscentedKalmanFilter
from edgepos.core.parameters import check_parameters

FILTERS: dict[str, type[GaussianFilter]] = {
    cls.name: cls
    for cls in (
        ExtendedKalmanFilter,
        UnscentedKalmanFilter,
        CubatureKalmanFilter,
        SquareRootUnscentedKalmanFilter,
    )
}


def make_filter(name: str, **params: Any) -> GaussianFilter:
    """Build a registered filter by name, its parameters checked against the filter's ``parameters``
    (``core.parameters``): a bad one is a ConfigurationError whose ``parameter`` names it."""
    try:
        cls = FILTERS[name]
    except KeyError:
        raise ConfigurationError(f"unknown filter {name!r}; known: {sorted(FILTERS)}") from None
    params = check_parameters(f"filter {name!r}", cls.parameters, params)
    try:
        return cls(**params)
    except TypeError as error:
        raise ConfigurationError(f"bad parameters for filter {name!r}: {error}") from None


__all__ = [
    "FILTERS",
    "CubatureKalmanFilter",
    "ExtendedKalmanFilter",
    "GaussianFilter",
    "SquareRootUnscentedKalmanFilter",
    "UnscentedKalmanFilter",
    "UpdateResult",
    "kalman_correct",
    "make_filter",
]
