"""Typed errors raised by the estimation core instead of returning non-finite numbers."""

from __future__ import annotations


class EstimationError(Exception):
    """A filter step could not be computed; the caller's state is left untouched."""


class NumericalError(EstimationError):
    """A matrix was singular, indefinite beyond repair, or a result was not finite."""


class ConfigurationError(EstimationError, ValueError):
    """A model, filter or pipeline was configured with values outside their domain."""
