"""Integrity options of a session and the RSU monitor of the ``rsu_imu`` pipeline (``core.integrity_bank``).

The options size the protection level every fix carries: the integrity risk per epoch, the alert
limit that puts a fix in alarm, the prior probability that one RSU is faulty, the false-alarm
probability the fault tests are sized to, whether and for how long a detected RSU is excluded, and
the sub-filters' process noise. Their defaults and the reasons for them are in docs/integrity.md.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from edgepos.core import layout
from edgepos.core import state as state_format
from edgepos.core.imm import Gaussian
from edgepos.core.integrity import (
    ALARM,
    IntegrityBudget,
    Protection,
)
from edgepos.core.integrity_bank import SeparationBank, budget_tables
from edgepos.core.integrity_run import stacked_tables
from edgepos.core.observations import Observation, RsuObservation
from edgepos.core.updates import RsuGyroEpoch
from edgepos.pipelines.base import MeasurementUse, OptionSpec

#: Default jerk spectral density of the sub-filters (m^2/s^5), chosen on seeds 0-99 of the RSU + IMU
#: scenario so that their position NEES is consistent (docs/integrity.md).
JERK_PSD = 10.0

INTEGRITY_SPECS: tuple[OptionSpec, ...] = (
    OptionSpec(
        "integrity",
        "boolean",
        True,
        "Run the integrity monitor: a protection level with every fix, RSU fault detection and exclusion "
        "(docs/integrity.md). It adds about a fifth to the CPU time of an epoch (one sub-filter per RSU in use "
        "beside the IMM); off, every fix's integrity is 'unavailable' and protection_level_m null.",
    ),
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
    OptionSpec(
        "fault_exclusion_s",
        "number",
        5.0,
        "How long (s) an RSU found faulty stays excluded before it is tried again.",
        0.0,
        3600.0,
    ),
    OptionSpec(
        "integrity_jerk_psd",
        "number",
        JERK_PSD,
        "Spectral density (m^2/s^5) of the white jerk of the constant-acceleration sub-filters the protection "
        "level runs one per RSU hypothesis (core.integrity_bank); larger is more conservative.",
        1e-6,
        1e4,
    ),
)


@dataclass(frozen=True)
class RsuIntegrity:
    """The session's integrity budget and whether a faulty RSU is excluded."""

    budget: IntegrityBudget
    exclusion: bool

    @staticmethod
    def of(options: Mapping[str, Any]) -> RsuIntegrity:
        """The monitor for a session's options (cached: sessions share a handful of option sets)."""
        return _monitor(
            options["integrity_risk"],
            options["false_alarm_probability"],
            options["fault_probability"],
            options["alert_limit_m"],
            bool(options["fault_exclusion"]),
        )


# The monitor and jerk density of the options last seen, by identity: a session's options are the dict
# ``rsu_imu`` decodes once per options key and shares (never changed), so consecutive epochs find it here
# for one comparison where ``RsuIntegrity.of`` reads five options and hashes them. One tuple, replaced
# whole: a thread reads a consistent entry.
_last: tuple[Mapping[str, Any] | None, RsuIntegrity | None, float] = (None, None, 0.0)


def _monitor_of(options: Mapping[str, Any]) -> tuple[RsuIntegrity, float]:
    """The monitor of a session's options (``RsuIntegrity.of``) and the sub-filters' jerk density."""
    global _last
    last = _last
    if last[0] is options:
        return last[1], last[2]  # type: ignore[return-value]  # set together with last[0]
    monitor, jerk_density = RsuIntegrity.of(options), options["integrity_jerk_psd"]
    _last = (options, monitor, jerk_density)
    return monitor, jerk_density


@functools.lru_cache(maxsize=256)
def _monitor(
    risk: float,
    false_alarm: float,
    fault: float,
    alert_limit: float,
    exclusion: bool,
) -> RsuIntegrity:
    return RsuIntegrity(IntegrityBudget(risk, false_alarm, fault, alert_limit), exclusion)


def warm_up_tables(max_hypotheses: int = 8) -> None:
    """Tabulate the radial bounds and test thresholds of the default options' budget for 0 to
    ``max_hypotheses`` sub-filters now (about 30 ms each, by quadrature), and their stacks for a run of
    epochs (``core.integrity_run.stacked_tables``), so that the first vehicles' epochs do not stall the
    filter thread computing them (the tables are cached per process)."""
    defaults = {spec.name: spec.default for spec in INTEGRITY_SPECS}
    budget = RsuIntegrity.of(defaults).budget
    for hypotheses in range(max_hypotheses + 1):
        budget_tables(budget, hypotheses)
        stacked_tables(budget, hypotheses + 1)


EXCLUDED = "excluded by fault detection"
_Result = TypeVar("_Result")


def _rsu_id(index: int, observations: Sequence[Observation]) -> str:
    observation = observations[index]
    assert isinstance(observation, RsuObservation)  # candidates are RSU observations
    return observation.rsu_id


def _fix(output: Gaussian) -> tuple[float, float, float, float, float]:
    """The horizontal position of a fix's Gaussian and its covariance: x, y, xx, xy, yy."""
    x, y = _position_index(output.components)
    mean, cov = output.mean, output.cov
    return mean.item(x), mean.item(y), cov.item(x, x), cov.item(x, y), cov.item(y, y)


@functools.lru_cache(maxsize=16)
def _position_index(components: tuple[int, ...]) -> tuple[int, int]:
    return components.index(layout.XP), components.index(layout.YP)


def bank_from_tail(tail: bytes) -> SeparationBank | None:
    """The integrity bank stored after a session's filter arrays (none in states written before it)."""
    if not tail:
        return None
    try:
        return SeparationBank.from_bytes(tail)
    except ValueError as error:
        raise state_format.StateFormatError(f"rsu_imu state is corrupt: {error}") from None


def start_bank(output: Gaussian, t: float) -> SeparationBank:
    """A bank whose reference starts at the fix ``output`` (its x, vx, ax, y, vy, ay; an acceleration the
    models lack gets zero with a 3 m/s^2 std)."""
    components = list(output.components)
    mean = np.zeros(6)
    cov = np.diag(np.full(6, 9.0))
    present = [(k, components.index(c)) for k, c in enumerate(layout.KINEMATIC) if c in components]
    target = [k for k, _ in present]
    source = [j for _, j in present]
    mean[target] = output.mean[source]
    cov[np.ix_(target, target)] = output.cov[np.ix_(source, source)]
    return SeparationBank.start(mean, cov, t)


def monitored_update(
    bank: SeparationBank | None,
    t: float,
    candidates: list[int],
    measured: RsuGyroEpoch,
    observations: Sequence[Observation],
    options: Mapping[str, Any],
    uses: dict[int, MeasurementUse],
    prior: Gaussian,
    remeasure: Callable[[list[int]], RsuGyroEpoch],
    correct: Callable[[RsuGyroEpoch], _Result],
    output_of: Callable[[_Result], Gaussian],
) -> tuple[_Result, list[int], RsuGyroEpoch, Protection, SeparationBank]:
    """One epoch's update with fault detection and exclusion and the fix's protection level.

    ``measured`` holds the ``candidates``' measurement arrays (and the epoch's gyro readings),
    ``remeasure(kept)`` gives them for fewer RSUs and ``correct(measured)`` runs the pipeline's update. The
    RSUs excluded earlier are left out; an RSU in use whose test over time (``core.integrity_bank``) fails
    is excluded for ``fault_exclusion_s`` and the epoch filtered again without it; a failed test that
    cannot be acted on (exclusion off, the only RSU, or an RSU not in use) puts the fix in alarm. Returns
    the update, the RSUs and measurements it used, the protection and the bank (started from the
    pipeline's ``prior`` of this epoch when the session has none yet)."""
    monitor, jerk_density = _monitor_of(options)
    if bank is not None and bank.excluded:
        held = bank.excluded_now(t)
        kept = [i for i in candidates if _rsu_id(i, observations) not in held]
        for i in [i for i in candidates if i not in kept]:
            until = bank.excluded[_rsu_id(i, observations)]
            uses[i] = MeasurementUse(i, "rsu", False, f"{EXCLUDED}: held out until t={until:.2f} s")
        if len(kept) < len(candidates):
            candidates, measured = kept, remeasure(kept)
    result = correct(measured)
    if bank is None:
        bank = start_bank(prior, t)
    in_use: list[str] = [observations[i].rsu_id for i in candidates]  # type: ignore[union-attr]  # RSUs all
    arrays = (measured.positions, measured.observed, measured.range_std, measured.bearing_std)
    output = output_of(result)
    protection, faulty = bank.epoch(
        t,
        jerk_density,
        in_use,
        arrays,
        output.mean,
        output.cov,
        _position_index(output.components),
        monitor.budget,
        prune=True,  # when no test failed: the usual epoch's prune decided by the kernel
    )
    if faulty is None:
        return result, candidates, measured, protection, bank
    if monitor.exclusion and faulty in in_use and len(candidates) > 1:
        index = candidates[in_use.index(faulty)]
        uses[index] = MeasurementUse(
            index,
            "rsu",
            False,
            f"{EXCLUDED}: filter separation {protection.statistic:.1f} sigma > {protection.threshold:.1f}",
        )
        candidates = [i for i in candidates if i != index]
        measured = remeasure(candidates)
        result = correct(measured)
        bank.exclude(faulty, t + options["fault_exclusion_s"])
        in_use.remove(faulty)
        protection, faulty = bank.protect_fix(_fix(output_of(result)), monitor.budget)
    if faulty is not None:  # a failed test not acted on: the fix is not to be trusted
        protection = Protection(
            protection.level, ALARM, protection.faulty, protection.statistic, protection.threshold
        )
    bank.prune(in_use)
    return result, candidates, measured, protection, bank
