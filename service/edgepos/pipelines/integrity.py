"""Integrity options of a session and the RSU monitor of the ``rsu_imu`` pipeline (``core.integrity``).

The options size the protection level every fix carries: the integrity risk per epoch, the alert
limit that puts a fix in alarm, the prior probability that one RSU is faulty, the false-alarm
probability the fault tests are sized to, and whether a detected RSU is excluded and the epoch
filtered again. Their defaults and the reasons for them are in docs/integrity.md.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from edgepos.core import layout
from edgepos.core.imm import Gaussian
from edgepos.core.integrity import IntegrityBudget, Protection, SourceEffect, protect, range_bearing_effect
from edgepos.core.observations import Observation, RsuObservation
from edgepos.pipelines.base import OptionSpec, Rsu

INTEGRITY_SPECS: tuple[OptionSpec, ...] = (
    OptionSpec(
        "integrity_risk",
        "number",
        1e-5,
        "Integrity risk per epoch: the probability that the horizontal error exceeds protection_level_m while "
        "the fix is not in alarm, faults included.",
        1e-9,
        0.1,
    ),
    OptionSpec(
        "alert_limit_m",
        "number",
        1.5,
        "Alert limit (m): a fix whose protection level exceeds it is in alarm (1.5 m: half a lane, what lane "
        "keeping tolerates).",
        0.0,
        1e4,
    ),
    OptionSpec(
        "fault_probability",
        "number",
        1e-4,
        "Prior probability that one RSU's range and bearing are faulty in an epoch (a wrong surveyed position, "
        "a reflection, a biased clock); sizes each fault hypothesis' share of the integrity risk.",
        1e-9,
        0.1,
    ),
    OptionSpec(
        "false_alarm_probability",
        "number",
        1e-4,
        "Probability per epoch that a fault-free epoch fails a fault test (the tests' thresholds): lower "
        "means fewer needless exclusions and a larger protection level.",
        1e-9,
        0.1,
    ),
    OptionSpec(
        "fault_exclusion",
        "boolean",
        True,
        "Exclude the RSU a failed fault test points at and filter the epoch again without it (one RSU per "
        "epoch); false: only report the alarm.",
    ),
)


@dataclass(frozen=True)
class RsuIntegrity:
    """The session's integrity budget, applied to one epoch's RSU measurements."""

    budget: IntegrityBudget
    exclusion: bool
    range_std: float
    bearing_std: float

    @staticmethod
    def of(options: Mapping[str, Any]) -> RsuIntegrity:
        """The monitor for a session's options (cached: sessions share a handful of option sets)."""
        return _monitor(
            options["integrity_risk"],
            options["false_alarm_probability"],
            options["fault_probability"],
            options["alert_limit_m"],
            bool(options["fault_exclusion"]),
            options["range_std"],
            options["bearing_std"],
        )

    def protect(
        self,
        output: Gaussian,
        candidates: Sequence[int],
        observations: Sequence[Observation],
        rsus: Sequence[Rsu | None],
    ) -> Protection:
        """Protection level and fault test of the posterior ``output`` shaped by the RSUs ``candidates``."""
        components = list(output.components)
        xi, yi = components.index(layout.XP), components.index(layout.YP)
        mean, cov = output.mean, output.cov
        x, y = float(mean[xi]), float(mean[yi])
        position_cov = ((float(cov[xi, xi]), float(cov[xi, yi])), (float(cov[yi, xi]), float(cov[yi, yi])))
        sources: list[SourceEffect] = []
        for i in candidates:
            observation, rsu = observations[i], rsus[i]
            assert isinstance(observation, RsuObservation) and rsu is not None  # candidates are RSUs in view
            sources.append(
                range_bearing_effect(
                    x,
                    y,
                    rsu.x,
                    rsu.y,
                    observation.range,
                    observation.bearing,
                    rsu.range_std or self.range_std,
                    rsu.bearing_std or self.bearing_std,
                )
            )
        return protect(position_cov, sources, self.budget)


@functools.lru_cache(maxsize=256)
def _monitor(
    risk: float,
    false_alarm: float,
    fault: float,
    alert_limit: float,
    exclusion: bool,
    range_std: float,
    bearing_std: float,
) -> RsuIntegrity:
    return RsuIntegrity(
        IntegrityBudget(risk, false_alarm, fault, alert_limit), exclusion, range_std, bearing_std
    )
