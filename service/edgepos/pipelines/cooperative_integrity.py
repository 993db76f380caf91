"""Integrity options and the fault monitor of the cooperative pipelines (``v2v_coop``, ``v2x_federated``).

Before an epoch's range update each neighbour ranged to is screened: one held out by an earlier
detection stays out until its hold ends, and one whose broadcast track took a step its own covariances
cannot explain (``core.cooperative_integrity.track_step_statistic``) is excluded and held out for
``fault_exclusion_s``. After the updates the fix is checked one source at a time (its own GNSS fix,
each neighbour ranged to) by solution separation; a neighbour that test points at is excluded, held out
alike, and the epoch's range update run again without it. A faulty own fix, or a fault that cannot be
excluded, puts the fix in alarm. The holds are plain data in the session's state ({neighbour id: until
t}, and the time of the last track point tested per neighbour). The options have rsu_imu's names; their defaults and why are in docs/integrity.md, "Cooperative
pipelines".
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from edgepos.core import gnss_bias
from edgepos.core.cooperative_integrity import (
    RangeSource,
    cooperative_protection,
    fix_effect,
    track_step_statistic,
)
from edgepos.core.gnss_bias import Bias
from edgepos.core.integrity import (
    ALARM,
    UNAVAILABLE,
    IntegrityBudget,
    Protection,
    SourceEffect,
    test_threshold,
)
from edgepos.core.observations import (
    GnssFixObservation,
    Observation,
    RsuRangeObservation,
    V2vRangeObservation,
)
from edgepos.pipelines.base import Environment, Fix, MeasurementUse, NeighbourTrack, OptionSpec
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
            "limit at every epoch, with the papers' options its bound does not hold (consistency_scale narrows "
            "that, docs/integrity.md), and it costs up to 60 % of an epoch. Off, every fix's integrity is "
            "'unavailable' and protection_level_m null."
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
        description="Exclude the neighbour a failed fault test points at (its broadcast track's step, or "
        "solution separation, which then runs the epoch's range update again without it) for "
        "fault_exclusion_s; false: only report the alarm.",
    ),
    dataclasses.replace(
        _SPECS["fault_exclusion_s"],
        description="How long (s) a neighbour found faulty stays excluded before it is tried again (0: the "
        "epoch of the detection only).",
    ),
)

#: What a session stored before the monitor existed goes on with: no monitor (and one stored with the
#: monitor before fault_exclusion_s existed excludes for the epoch only, as it did).
LEGACY_INTEGRITY = {
    **{spec.name: spec.default for spec in COOPERATIVE_INTEGRITY_SPECS},
    "integrity": False,
    "fault_exclusion_s": 0.0,
}


@functools.lru_cache(maxsize=256)
def _budget(risk: float, false_alarm: float, fault: float, alert_limit: float) -> IntegrityBudget:
    return IntegrityBudget(risk, false_alarm, fault, alert_limit)


def budget_of(options: Mapping[str, Any], risk_left: float = 1.0) -> IntegrityBudget:
    """The session's budget (cached: sessions share a handful of option sets), with ``risk_left`` of its
    integrity risk (what another bound has not spent)."""
    return _budget(
        options["integrity_risk"] * risk_left,
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


#: How long (s) a neighbour's last tested track point is remembered after it (a track that went quiet longer
#: is tested from its newest step again when it returns).
SEEN_S = 60.0


def _track_jump(
    track: NeighbourTrack | None, seen: float | None, accel_std: float
) -> tuple[float, float | None]:
    """The largest step statistic of the track's points newer than ``seen`` (the newest step alone when
    None), each against the point before it, and the newest point's time."""
    if track is None or len(track.points) < 2:
        return 0.0, None if track is None or not track.points else track.points[-1].t
    points = track.points
    worst = 0.0
    for k in range(len(points) - 1, 0, -1):
        later, earlier = points[k], points[k - 1]
        if seen is not None and later.t <= seen:
            break
        statistic = track_step_statistic(
            (earlier.t, earlier.x, earlier.y, earlier.vx, earlier.vy, earlier.cov),
            (later.t, later.x, later.y, later.cov),
            accel_std,
        )
        worst = max(worst, statistic)
        if seen is None:
            break
    return worst, points[-1].t


def screen_neighbours(
    options: Mapping[str, Any],
    held: dict[str, float],
    seen: dict[str, float],
    epoch: Sequence[int],
    observations: Sequence[Observation],
    environment: Environment,
    t: float,
    uses: dict[int, MeasurementUse],
) -> tuple[frozenset[str], bool]:
    """The neighbours to leave out of this epoch's range update, and whether a failed test could not be
    acted on (the fix is then in alarm).

    A neighbour (or RSU) held out (``held``: id -> until t) stays out; one whose broadcast track took a new step
    (newer than ``seen``: id -> the last point tested) beyond its covariances' bound (the threshold of
    ``false_alarm_probability`` split over the neighbours tested) is excluded and held for
    ``fault_exclusion_s``. Both dicts are updated in place; the ranges' uses say why."""
    for peer in [peer for peer, until in held.items() if until <= t]:
        del held[peer]
    for peer in [peer for peer, last in seen.items() if last < t - SEEN_S]:
        del seen[peer]
    peers: dict[str, list[int]] = {}
    rsus: dict[str, list[int]] = {}
    for i in epoch:
        observation = observations[i]
        if isinstance(observation, V2vRangeObservation):
            peers.setdefault(observation.peer_vehicle_id, []).append(i)
        elif isinstance(observation, RsuRangeObservation) and observation.rsu_id in held:
            rsus.setdefault(observation.rsu_id, []).append(i)
    excluded: set[str] = set()
    alarm = False
    threshold = test_threshold(options["false_alarm_probability"], len(peers))
    for peer, indices in [*peers.items(), *rsus.items()]:
        statistic, newest = 0.0, None
        if peer in peers:
            statistic, newest = _track_jump(
                environment.neighbour(peer), seen.get(peer), options["neighbour_accel_std"]
            )
        if newest is not None:
            seen[peer] = newest
        if peer in held:
            reason = f"{EXCLUDED}: held out until t={held[peer]:.2f} s"
        else:
            if statistic <= threshold:
                continue
            if not options["fault_exclusion"]:
                alarm = True
                continue
            reason = f"{EXCLUDED}: broadcast track stepped {statistic:.1f} sigma > {threshold:.1f}"
            hold(options, held, peer, t)
        excluded.add(peer)
        for i in indices:
            uses[i] = MeasurementUse(i, observations[i].kind, False, reason)
    return frozenset(excluded), alarm


def hold(options: Mapping[str, Any], held: dict[str, float], source: str, t: float) -> None:
    """Hold ``source`` out for ``fault_exclusion_s`` from ``t`` (0: nothing to hold beyond the epoch)."""
    if options["fault_exclusion_s"] > 0.0:
        held[source] = t + options["fault_exclusion_s"]


def monitor(
    options: Mapping[str, Any],
    fix_of: Callable[[], tuple[float, float, Sequence[Sequence[float]]]],
    fix_source: Callable[[float, float], SourceEffect | None],
    ranges: list[tuple[int, RangeSource]],
    redo: Callable[[frozenset[str]], list[tuple[int, RangeSource]]],
    uses: dict[int, MeasurementUse],
    held: dict[str, float],
    t: float,
    scale: float = 1.0,
    scale_risk_share: float = 0.0,
) -> Protection:
    """Test the epoch's fix and, when a neighbour is faulty and exclusion is on, exclude it.

    ``fix_of()`` gives the current fix's x, y and 2x2 position covariance, ``fix_source(x, y)`` the GNSS
    fix source at it, ``ranges`` the ranges used (observation index, source) and ``redo(excluded)`` runs
    the range update again from the same prior without the ``excluded`` sources (neighbours or RSUs by
    id, beside those screened out before), returning the ranges it used. The measurement uses of an
    excluded source's ranges say so, and it is held out (``held``) for ``fault_exclusion_s`` from ``t``.
    ``scale``: the filter's consistency scale on the protection level's error bounds (1: none; the tests
    use the filter's own covariance either way, ``core.cooperative_integrity.protect_sources``);
    ``scale_risk_share``: the share of ``integrity_risk`` that ``scale``'s confidence bound spends, the
    protection level being sized with the rest (``pipelines.cooperative_consistency``)."""
    budget = budget_of(options, 1.0 - scale_risk_share)
    x, y, cov = fix_of()
    sources = [source for _, source in ranges]
    own = fix_source(x, y)
    protection = cooperative_protection(x, y, cov, own, sources, budget, scale)
    offset = 1 if own is not None else 0
    if protection.faulty is None or protection.faulty < offset:
        return protection
    if not options["fault_exclusion"]:
        return protection  # already in alarm: a failed test
    faulty = sources[protection.faulty - offset].neighbour
    statistic, threshold = protection.statistic, protection.threshold
    kept = redo(frozenset([faulty]))
    hold(options, held, faulty, t)
    for index, source in ranges:
        if source.neighbour == faulty:
            uses[index] = MeasurementUse(
                index,
                uses[index].kind,
                False,
                f"{EXCLUDED}: solution separation {statistic:.1f} sigma > {threshold:.1f}",
            )
    x, y, cov = fix_of()
    after = cooperative_protection(x, y, cov, fix_source(x, y), [s for _, s in kept], budget, scale)
    if after.faulty is not None:  # a second fault: beyond the one-at-a-time model
        return Protection(after.level, ALARM, after.faulty, after.statistic, after.threshold)
    return after


def with_protection(fix: Fix, protection: Protection | None) -> Fix:
    """The fix with its protection level and integrity state (unavailable without a monitor)."""
    if protection is None:
        return dataclasses.replace(fix, protection_level=None, integrity=UNAVAILABLE)
    return dataclasses.replace(fix, protection_level=protection.level, integrity=protection.state)
