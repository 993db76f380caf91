"""Typed errors raised by the estimation core instead of returning non-finite numbers."""

from __future__ import annotations


class EstimationError(Exception):
    """A filter step could not be computed; the caller's state is left untouched."""


class NumericalError(EstimationError):
    """A matrix was singular, indefinite beyond repair, or a result was not finite."""


class ConfigurationError(EstimationError, ValueError):
    """A model, filter or pipeline was configured with values outside their domain.

    ``parameter``: the name of the offending parameter when one is to blame (None otherwise)."""

    def __init__(self, message: str, parameter: str | None = None) -> None:
        super().__init__(message)
        self.parameter = parameter

    def __reduce__(self) -> tuple[type[ConfigurationError], tuple[str, str | None]]:
        # Pickled whole (heavy batches run in worker processes): the default keeps only the message.
        return (type(self), (str(self), self.parameter))
