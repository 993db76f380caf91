"""Integrity options and the fault monitor of the cooperative pipelines (``v2v_coop``, ``v2x_federated``).

After an epoch's updates the fix is checked one source at a time (its own GNSS fix, each neighbour
ranged to) by solution separation (``core.cooperative_integrity``). A neighbour the test points at is
excluded and the epoch's range update run again without it (exclusion lasts the epoch: the neighbour
is tested afresh at the next one, so the session's state gains nothing); a faulty own fix, or a fault
that cannot be excluded, puts the fix in alarm. The options have rsu_imu's names; their defaults and
why are in docs/integrity.md, "Cooperative pipelines".
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from edgepos.core import gnss_bias
from edgepos.core.cooperative_integrity import RangeSource, cooperative_protection, fix_effect
from edgepos.core.gnss_bias import Bias
from edgepos.core.integrity import ALARM, UNAVAILABLE, IntegrityBudget, Protection, SourceEffect
from edgepos.core.observations import GnssFixObservation
from edgepos.pipelines.base import Fix, MeasurementUse, OptionSpec
from edgepos.pipelines.integrity import EXCLUDED, INTEGRITY_SPECS

_SPECS = {spec.name: spec for spec in INTEGRITY_SPECS}

COOPERATIVE_INTEGRITY_SPECS: tuple[OptionSpec, ...] = (
    dataclasses.replace(
        _SPECS["integrity"],
        default=False,
        description=(
            "Run the integrity monitor: a protection level with every fix, detection of a faulty neighbour "
            "or own GNSS fix by solution separation, and exclusion of a faulty neighbour (docs/integrity.md). "
            "Off by default: on the honest defaults its protection level (about 10 m) is above the 5 m alert "
            "limit at every epoch, with the papers' options its bound does not hold (docs/integrity.md), and it "
            "costs up to 60 % of an epoch. Off, every fix's integrity is 'unavailable' and protection_level_m null."
        ),
    ),
    _SPECS["integrity_risk"],
    dataclasses.replace(
        _SPECS["alert_limit_m"],
        default=5.0,
        description="Alert limit (m): a fix whose protection level exceeds it is in alarm (5 m: the issue's "
        "limit for pipelines that fuse GNSS fixes).",
    ),
    dataclasses.replace(
        _SPECS["fault_probability"],
        description="Prior probability that one source (the GNSS fix, or one neighbour's published position) "
        "is faulty in an epoch; sizes each fault hypothesis' share of the integrity risk.",
    ),
    _SPECS["false_alarm_probability"],
    dataclasses.replace(
        _SPECS["fault_exclusion"],
        description="Exclude the neighbour a failed fault test points at and run the epoch's range update "
        "again without it (one neighbour per epoch, tested afresh at the next); false: only report the alarm.",
    ),
)

#: What a session stored before the monitor existed goes on with: no monitor.
LEGACY_INTEGRITY = {
    **{spec.name: spec.default for spec in COOPERATIVE_INTEGRITY_SPECS},
    "integrity": False,
}


@functools.lru_cache(maxsize=256)
def _budget(risk: float, false_alarm: float, fault: float, alert_limit: float) -> IntegrityBudget:
    return IntegrityBudget(risk, false_alarm, fault, alert_limit)


def budget_of(options: Mapping[str, Any]) -> IntegrityBudget:
    """The session's budget (cached: sessions share a handful of option sets)."""
    return _budget(
        options["integrity_risk"],
        options["false_alarm_probability"],
        options["fault_probability"],
        options["alert_limit_m"],
    )


def fix_source(
    options: Mapping[str, Any], bias: Bias, fix: GnssFixObservation | None, x: float, y: float
) -> SourceEffect | None:
    """The epoch's GNSS fix as a fault hypothesis at (x, y): its white variance beside the bias state's
    covariance (None when the epoch had no fix)."""
    if fix is None:
        return None
    std = fix.std if fix.std is not None else options["gps_std"]
    sigma = options["gnss_bias_std"]
    white = gnss_bias.white_variance(std, sigma) if sigma > 0.0 else std * std
    return fix_effect(x, y, (fix.x, fix.y), bias.mean, bias.cov, white)


def monitor(
    options: Mapping[str, Any],
    fix_of: Callable[[], tuple[float, float, Sequence[Sequence[float]]]],
    fix_source: Callable[[float, float], SourceEffect | None],
    ranges: list[tuple[int, RangeSource]],
    redo: Callable[[frozenset[str]], list[tuple[int, RangeSource]]],
    uses: dict[int, MeasurementUse],
) -> Protection:
    """Test the epoch's fix and, when a neighbour is faulty and exclusion is on, exclude it.

    ``fix_of()`` gives the current fix's x, y and 2x2 position covariance, ``fix_source(x, y)`` the GNSS
    fix source at it, ``ranges`` the ranges used (observation index, source) and ``redo(excluded)`` runs
    the range update again from the same prior without the ``excluded`` sources (neighbours or RSUs by
    id), returning the ranges it used. The measurement uses of an excluded source's ranges say so."""
    budget = budget_of(options)
    x, y, cov = fix_of()
    sources = [source for _, source in ranges]
    own = fix_source(x, y)
    protection = cooperative_protection(x, y, cov, own, sources, budget)
    offset = 1 if own is not None else 0
    if protection.faulty is None or protection.faulty < offset:
        return protection
    if not options["fault_exclusion"]:
        return protection  # already in alarm: a failed test
    faulty = sources[protection.faulty - offset].neighbour
    statistic, threshold = protection.statistic, protection.threshold
    kept = redo(frozenset([faulty]))
    for index, source in ranges:
        if source.neighbour == faulty:
            uses[index] = MeasurementUse(
                index,
                uses[index].kind,
                False,
                f"{EXCLUDED}: solution separation {statistic:.1f} sigma > {threshold:.1f}",
            )
    x, y, cov = fix_of()
    after = cooperative_protection(x, y, cov, fix_source(x, y), [s for _, s in kept], budget)
    if after.faulty is not None:  # a second fault: beyond the one-at-a-time model
        return Protection(after.level, ALARM, after.faulty, after.statistic, after.threshold)
    return after


def with_protection(fix: Fix, protection: Protection | None) -> Fix:
    """The fix with its protection level and integrity state (unavailable without a monitor)."""
    if protection is None:
        return dataclasses.replace(fix, protection_level=None, integrity=UNAVAILABLE)
    return dataclasses.replace(fix, protection_level=protection.level, integrity=protection.state)
