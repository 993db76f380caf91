"""The ``gnss_tight`` integrity monitor: its session options, and the glue between the pipeline's epoch
and the solution-separation RAIM of gnss/raim.py (fault detection and exclusion on the pseudoranges before
the filter's update, the protection level from its posterior after it). Formulas and the defaults' reasons
are in docs/integrity.md ("GNSS (gnss_tight)")."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from edgepos.core.integrity import UNAVAILABLE, Protection, radial_factor_table
from edgepos.core.measurements.gnss_kernel import pseudoranges_at
from edgepos.core.measurements.pseudorange import PseudorangeModel
from edgepos.core.motion import riss as layout
from edgepos.gnss.raim import RaimBudget, Separations, protection, separations
from edgepos.pipelines.base import MeasurementUse, OptionSpec
from edgepos.pipelines.integrity import EXCLUDED
from edgepos.pipelines.integrity import INTEGRITY_SPECS as RSU_INTEGRITY_SPECS

_RSU_SPECS = {spec.name: spec for spec in RSU_INTEGRITY_SPECS}  # the options that mean the same as rsu_imu's
DEFAULT_INFLATION = 5.0
"""Default covariance inflation k; see the option's description and docs/integrity.md for the measurement."""
WHITE_INFLATION = 8.0
"""k for the filter's own (white-error) covariance, the default before error_correlation existed: sessions
stored before then, which report that covariance, keep it."""

INTEGRITY_SPECS: tuple[OptionSpec, ...] = (
    OptionSpec(
        "integrity",
        "boolean",
        True,
        "Run the integrity monitor: solution-separation RAIM (one-satellite and one-constellation fault "
        "hypotheses) with the filter, a protection level with every fix, fault detection and exclusion "
        "(docs/integrity.md, GNSS). Off: every fix's integrity is 'unavailable' and protection_level_m null.",
    ),
    _RSU_SPECS["integrity_risk"],
    dataclasses.replace(
        _RSU_SPECS["alert_limit_m"],
        default=5.0,
        description="Alert limit (m): a fix whose protection level exceeds it is in alarm (5 m: which road a "
        "vehicle is on, what a GNSS-only fix can support).",
    ),
    OptionSpec(
        "satellite_fault_probability",
        "number",
        1e-4,
        "Prior probability per epoch that one given satellite's pseudorange is faulty beyond its noise model "
        "and the pipeline's own screening (a reflection, an orbit or clock fault); sizes each one-satellite "
        "hypothesis' share of the integrity risk.",
        1e-9,
        0.1,
    ),
    OptionSpec(
        "constellation_fault_probability",
        "number",
        1e-4,
        "Prior probability per epoch that one constellation is faulty as a whole (a wrong broadcast, a "
        "common clock or ephemeris fault; ARAIM's P_const); sizes each one-constellation hypothesis' share.",
        1e-9,
        0.1,
    ),
    _RSU_SPECS["false_alarm_probability"],
    dataclasses.replace(
        _RSU_SPECS["fault_exclusion"],
        description="Exclude the satellite or constellation a failed separation test points at from the "
        "epoch's update and test again (one exclusion per epoch); false: only report the alarm.",
    ),
    OptionSpec(
        "integrity_inflation",
        "number",
        DEFAULT_INFLATION,
        "Factor on the fix's covariance (the prediction's and the posterior's, as error_correlation reports "
        "them) the protection level is computed from: the error model holds on average, not on every stretch "
        "of a drive (multipath comes and goes). 5: with error_correlation gauss_markov the worst 30-epoch "
        "mean NEES on the first half of tests/data/gnss-rover needs 3 (6.1 / 2, without the carrier), and "
        "other minutes of that drive (mean NEES 15 with the white covariance, issue 21; the factor multiplies "
        "that covariance by 1.45 on this recording without the carrier) would need 5 (docs/integrity.md); "
        "the adaptive noise_level, which only raises the covariance, lowers the first half's need to 2.3. "
        "With error_correlation white use 8.",
        1.0,
        1000.0,
    ),
)

_DEFAULTS = {spec.name: spec.default for spec in INTEGRITY_SPECS}
_POSITION_BLOCK = np.ix_([layout.NORTH, layout.EAST, layout.UP], [layout.NORTH, layout.EAST, layout.UP])
"""The position block's index arrays, built once (``np.ix_`` costs more than the indexing it serves)."""


def _option(options: Mapping[str, Any], name: str) -> Any:
    """An integrity option; sessions stored before the monitor existed get the defaults (k of the white
    covariance when they also predate error_correlation)."""
    if name == "integrity_inflation" and name not in options and "error_correlation" not in options:
        return WHITE_INFLATION
    return options.get(name, _DEFAULTS[name])


def enabled(options: Mapping[str, Any]) -> bool:
    return bool(_option(options, "integrity"))


def budget_of(options: Mapping[str, Any]) -> RaimBudget:
    return RaimBudget(
        float(_option(options, "integrity_risk")),
        float(_option(options, "false_alarm_probability")),
        float(_option(options, "satellite_fault_probability")),
        float(_option(options, "constellation_fault_probability")),
        float(_option(options, "alert_limit_m")),
        float(_option(options, "integrity_inflation")),
    )


WARM_HYPOTHESES = range(8, 33)
"""Hypothesis counts (satellites in the update + constellations) whose radial tables the service computes
at start-up: 5 to 29 satellites with three constellations, 8 to 32 with one, what the recording in
tests/data/gnss-rover and a car under open sky give on the defaults."""


def warm_up_gnss_tables(hypotheses: Sequence[int] = WARM_HYPOTHESES) -> None:
    """Tabulate the protection level's radial bounds of the default budget for each hypothesis count now:
    each new count costs about 50 ms of quadrature (core.integrity's tables, cached per process) the first
    time an epoch has it, which would stall the filter thread in the middle of a drive."""
    budget = budget_of({})
    fault_free = 0.5 * budget.integrity_risk
    radial_factor_table(fault_free)
    for count in hypotheses:
        for probability in {budget.satellite_fault_probability, budget.constellation_fault_probability}:
            radial_factor_table(fault_free / count / probability)


def linearisation_ranges(
    anchor: Any, centre: np.ndarray, sat_position: np.ndarray, systems: Sequence[str], known: np.ndarray
) -> np.ndarray:
    """Row 0: the pseudoranges (n,) predicted at ``centre``, which the epoch's tests compare with (the prefit
    residuals of every hypothesis); rows 1-3: their derivatives (n,) by north, east and up, by 1 m differences
    (the ranges are linear over a metre to 1e-7 m). One model for all the rows and hypotheses of an epoch.

    By the compiled kernel (core/measurements/gnss_kernel.py ``pseudoranges_at``), which computes each
    state's ranges alone, as the tests do when they predict for themselves. Without it (``EDGEPOS_NUMBA=0``)
    the numpy model, row 0 evaluated on its own: the four-state matrix product rounds differently (in the
    last bit) from the one-state one the tests use alone, and the filters amplify such bits over epochs."""
    states = np.repeat(centre[None, :], 4, axis=0)
    for k, index in enumerate((layout.NORTH, layout.EAST, layout.UP)):
        states[k + 1, index] += 1.0
    compiled = pseudoranges_at(anchor, states, sat_position, systems, known)
    if compiled is not None:  # the kernel: each state's ranges alone, row 0 as a one-state call gives
        compiled[1:] -= compiled[0]
        return compiled
    model = PseudorangeModel.build(anchor, sat_position, list(systems), known, np.ones(len(known)))
    predicted: np.ndarray = model.predict(states)
    jacobian = predicted[1:] - predicted[0]
    predicted[0] = model.predict(centre)
    predicted[1:] = jacobian
    return predicted


def jacobian(ranges: np.ndarray, systems: Sequence[str]) -> np.ndarray:
    """d pseudorange / d (north, east, up, clock per constellation in ``groups`` order) from the rows'
    :func:`linearisation_ranges`."""
    column = {system: 3 + k for k, system in enumerate(sorted(set(systems)))}
    h = np.zeros((len(systems), 3 + len(column)))
    h[:, :3] = ranges[1:].T
    h[np.arange(len(systems)), [column[system] for system in systems]] = 1.0
    return h


def detect_and_exclude(
    options: Mapping[str, Any],
    anchor: Any,
    centre: np.ndarray,
    predicted_cov: np.ndarray,
    sat_position: np.ndarray,
    system_of_row: Sequence[str],
    known: np.ndarray,
    pseudorange: np.ndarray,
    std: np.ndarray,
    rows: np.ndarray,
    indices: Sequence[int],
    names: Sequence[str],
    uses: dict[int, MeasurementUse],
    ranges: np.ndarray | None = None,
) -> tuple[np.ndarray, Separations]:
    """Test the epoch's pseudoranges ``rows`` (after the pipeline's screening) against the prediction
    ``centre``; with exclusion on, leave out the satellite or constellation the worst failed test points at
    and test again. Returns the rows to update with and their separations (a test that still fails puts
    the fix in alarm). ``ranges``: :func:`linearisation_ranges` of every row when the caller has them."""
    budget = budget_of(options)
    prior = predicted_cov[_POSITION_BLOCK]
    if ranges is None:
        ranges = linearisation_ranges(anchor, centre, sat_position, system_of_row, known)

    def separate(kept: np.ndarray) -> Separations:
        systems = [system_of_row[r] for r in kept]
        if kept.size == 0:
            return Separations(False, (), 0.0)
        at = ranges[:, kept]
        z = pseudorange[kept] - at[0]
        return separations(jacobian(at, systems), systems, z, std[kept], prior, budget)

    result = separate(rows)
    worst = result.worst() if result.available else None
    if worst is None or not bool(_option(options, "fault_exclusion")):
        return rows, result
    # the worst satellite; when the epoch still fails without it, the worst constellation instead
    candidates = [worst]
    constellation = result.worst(size=2)
    if constellation is not None and constellation[0] != worst[0]:
        candidates.append(constellation)
    tried = []
    for index, statistic in candidates:
        kept = np.delete(rows, list(result.hypotheses[index][0]))
        tried.append((index, statistic, kept, separate(kept)))
        if tried[-1][3].available and tried[-1][3].worst() is None:
            break
    else:  # neither clears the epoch: exclude the satellite, and the retest's failure is the alarm
        del tried[1:]
    index, statistic, kept, retest = tried[-1]
    left_out = result.hypotheses[index][0]
    excluded = rows[list(left_out)]
    what = (
        names[int(excluded[0])] if len(left_out) == 1 else f"constellation {system_of_row[int(excluded[0])]}"
    )
    for r in excluded:
        i = indices[int(r)]
        uses[i] = MeasurementUse(
            i,
            "pseudorange",
            False,
            f"{EXCLUDED}: {what} separation {statistic:.1f} sigma > {result.threshold:.1f}",
        )
    return kept, retest


def fix_protection(
    separations_: Separations | None,
    position_cov: Sequence[Sequence[float]] | None,
    options: Mapping[str, Any],
) -> Protection:
    """The protection of a fix with horizontal covariance ``position_cov`` (east, north); unavailable
    without separations (the monitor off, or no pseudorange in the update)."""
    if separations_ is None or position_cov is None:
        return Protection(None, UNAVAILABLE)
    return protection(separations_, np.asarray(position_cov, float), budget_of(options))
