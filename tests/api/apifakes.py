"""Pipelines for tests that need the pipeline to misbehave or to be observed: each wraps the real
rsu_imu pipeline and changes one thing."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence

from edgepos.core.errors import ConfigurationError, EstimationError, NumericalError
from edgepos.core.observations import Observation
from edgepos.pipelines.base import Environment, Fix
from edgepos.pipelines.rsu_imu import RsuImuPipeline


class FailingPipeline(RsuImuPipeline):
    """Raises the estimation core's error on every batch."""

    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        raise NumericalError("innovation covariance is not positive definite")


class ResolveFailingPipeline(RsuImuPipeline):
    """Its estimation core refuses the options with its own error type."""

    def resolve_options(self, options):
        raise ConfigurationError("process noise must be positive")


class CreateFailingPipeline(RsuImuPipeline):
    """Refuses to create a state (as the core does for parameters outside their domain)."""

    def create(self, options, initial):
        raise EstimationError("initial covariance is singular")


class RsuOnlyPipeline(RsuImuPipeline):
    """Declares that it uses RSU measurements only."""

    measurement_kinds = ("rsu",)


class BrokenPipeline(RsuImuPipeline):
    """Has a bug: raises an unexpected exception (what the catch-all 500 is for)."""

    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        raise RuntimeError("bug with a secret-looking detail")


class GatedPipeline(RsuImuPipeline):
    """Records every call and, when ``gate`` is set, blocks in process() until it is opened."""

    def __init__(self) -> None:
        self.gate: threading.Event | None = None
        self.entered = threading.Event()
        self.calls: list[tuple[float, float]] = []
        self.timed_out = False
        self._lock = threading.Lock()

    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        start = time.monotonic()
        self.entered.set()
        if self.gate is not None and not self.gate.wait(timeout=20.0):
            self.timed_out = True
        result = super().process(state, observations, environment)
        with self._lock:
            self.calls.append((start, time.monotonic()))
        return result
