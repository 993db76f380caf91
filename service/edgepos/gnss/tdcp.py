"""Time-differenced carrier phase (TDCP): the receiver's displacement between consecutive epochs. Pure numpy.

While a satellite's tracking loop holds lock, its carrier phase (cycles; RINEX sign, growing with the range)
keeps its integer ambiguity, so between epochs k-1 and k it changes by the change of

    lambda L = rho(s, x) - c dts + T - I + c dtr + lambda N + (mm noise, cm multipath)

(``rho`` the Sagnac range from the receiver ``x`` to the satellite ``s`` at its transmit time, ``dts`` the
satellite clock, ``T`` and ``I`` the troposphere delay and the ionosphere advance, ``dtr`` the receiver
clock, ``N`` the ambiguity). The satellite's terms come from the broadcast orbit at both epochs; with
``x_k = x_{k-1} + d`` and ``x_{k-1}`` known to metres (an error e moves each difference by the change of
the line of sight, about 1.5e-4 e per second: sub-millimetre), each satellite's

    y = lambda (L_k - L_{k-1}) - [rho_k(x_{k-1}) - c dts_k + T_k - I_k] + [rho_{k-1}(x_{k-1}) - c dts_{k-1}
        + T_{k-1} - I_{k-1}] = -u_k . d + c (dtr_k - dtr_{k-1})

(``u_k`` the unit vector to the satellite) is linear in the displacement ``d`` and one receiver clock change
common to every constellation (the receiver has one oscillator; its inter-system biases are constant).
Weighted least squares over the satellites with continuous phase gives ``d`` to centimetres, where code
gives metres: the trajectory's shape between epochs, which the filter then uses as its motion
(pipelines/gnss_tdcp.py), so that it averages code errors over the whole track and not per satellite.

A slipped satellite's difference carries whole cycles (19-20 cm each) and a reflected signal's follows the
reflected path's change: both are caught by the chi-square test of the fit's residuals (the worst
standardised residual excluded while it fails, as the code's snapshot test does), besides the loss-of-lock
indicator, the Doppler-predicted phase change (``gnss/carrier.py``'s test) and the interval. Fewer than
``min_satellites`` consistent differences (4 unknowns and one redundancy to test them): no displacement.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from edgepos.gnss.orbits import sagnac_range

DEFAULT_PHASE_STD_M = 0.05
"""Chosen on the first half of tests/data/gnss-rover (docs/gnss.md, the pipeline's tdcp_phase_std_m)."""
DEFAULT_GATE_PROBABILITY = 0.999
DEFAULT_MIN_SATELLITES = 5
_UNKNOWNS = 4
MAX_CONDITION = 1e12
"""Largest condition number (infinity norm) of the fit's normal matrix: beyond it the satellites' geometry
does not fix the displacement (an exactly singular matrix inverts to rounding noise of 1e16 and more)."""
MIN_SIN_ELEVATION = math.sin(math.radians(10.0))
"""The differences' std is ``phase_std_m`` / sin(elevation) with the elevation floored at 10 deg."""

DIFFERENCED, NO_PREVIOUS, LOSS_OF_LOCK, GAP, SLIP, NO_PHASE = range(6)
"""Why a row's phase was or was not differenced (:func:`slip_reason`'s order, then no phase this epoch): the
codes the compiled form (pipelines/gnss_tdcp_kernel.py) returns, worded by :func:`slip_text`."""


@dataclass(frozen=True)
class TdcpConfig:
    """The difference's noise (``phase_std_m`` at zenith, divided by sin(elevation)), the fit's chi-square
    probability, the fewest differences it solves with, and the slip tests' thresholds (as the Hatch
    filter's: cycles per second off the Doppler, longest interval)."""

    phase_std_m: float = DEFAULT_PHASE_STD_M
    gate_probability: float = DEFAULT_GATE_PROBABILITY
    min_satellites: int = DEFAULT_MIN_SATELLITES
    slip_cycles_per_s: float = 5.0
    max_gap_s: float = 5.0


class PhaseHistory:
    """The previous epoch's phases: its time ``t``, the receiver position the terms were evaluated at
    (ECEF, m), the satellites ``sats`` and per satellite a row [cycles, model term] of ``table`` (k, 2), the
    term rho(s, x) - c dts + T - I (m). Rows in the order they were kept (the epoch's), so the session keeps
    and stores the arrays as they are: no per-satellite objects, no sorting, between epochs."""

    __slots__ = ("receiver", "sats", "t", "table")

    def __init__(
        self,
        t: float | None = None,
        receiver: tuple[float, float, float] | None = None,
        sats: Sequence[str] = (),
        table: np.ndarray | None = None,
    ) -> None:
        self.t = t
        self.receiver = receiver
        self.sats = tuple(sats)
        self.table: np.ndarray = np.zeros((0, 2)) if table is None else table

    @property
    def phases(self) -> dict[str, tuple[float, float]]:
        """Per satellite (cycles, term): the numpy reference's view of the table."""
        return {s: (row[0], row[1]) for s, row in zip(self.sats, self.table.tolist(), strict=True)}

    def rows(self, sats: Sequence[str]) -> np.ndarray:
        """Per satellite of ``sats``, its row of the table (-1: none)."""
        where = {s: k for k, s in enumerate(self.sats)}
        return np.array([where.get(s, -1) for s in sats], dtype=np.int64)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PhaseHistory):
            return NotImplemented
        return (
            self.t == other.t
            and self.receiver == other.receiver
            and self.sats == other.sats
            and np.array_equal(self.table, other.table)
        )

    __hash__ = None  # type: ignore[assignment]

    def to_parts(self) -> tuple[list[float] | None, list[str], np.ndarray]:
        """[t, x, y, z] (None when empty), the satellite ids and the (k, 2) table: the state's byte form."""
        if self.t is None or self.receiver is None:
            return None, list(self.sats), self.table
        return [self.t, *self.receiver], list(self.sats), self.table

    @classmethod
    def from_parts(cls, head: Sequence[float] | None, sats: Sequence[str], table: np.ndarray) -> PhaseHistory:
        """Inverse of :meth:`to_parts` (states written with the satellites sorted decode alike); raises
        ValueError when the parts do not fit together."""
        rows = np.asarray(table, dtype=float).reshape(len(sats), 2)
        if head is None:
            if sats:
                raise ValueError("phases without their epoch")
            return cls()
        if len(head) != 4:
            raise ValueError(f"expected [t, x, y, z], got {len(head)} numbers")
        t, x, y, z = (float(v) for v in head)
        return cls(t, (x, y, z), [str(s) for s in sats], rows)


@dataclass(frozen=True)
class Displacement:
    """The fit: displacement ``d`` (ECEF, m) since the history's epoch, its covariance (3 x 3), the clock
    change (m), and per input row None when its difference was used or why it was not; ``d`` is None when
    the epoch gave no displacement (``why`` says why)."""

    d: np.ndarray | None
    cov: np.ndarray | None
    clock_m: float
    reasons: list[str | None]
    why: str | None


Fit = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str | None], TdcpConfig], Displacement]
"""The least-squares fit :func:`displacement` runs: :func:`fit_rows`, or the compiled form
(pipelines/gnss_tdcp_kernel.py) the pipeline passes."""


def model_terms(
    receiver: np.ndarray,
    sat_position: np.ndarray,
    sat_clock_s: np.ndarray,
    troposphere_m: np.ndarray,
    ionosphere_m: np.ndarray,
    speed_of_light: float,
) -> np.ndarray:
    """Each row's rho(s, x) - c dts + T - I at ``receiver`` (the carrier phase's model without the receiver
    clock and the ambiguity; the ionosphere advances the phase)."""
    terms: np.ndarray = (
        sagnac_range(sat_position, receiver) - speed_of_light * sat_clock_s + troposphere_m - ionosphere_m
    )
    return terms


def slip_reason(
    previous: tuple[float, float] | None,
    dt: float,
    cycles: float,
    doppler_hz: float,
    lli: int,
    config: TdcpConfig,
) -> str | None:
    """Why a satellite's phase cannot be differenced with its ``previous`` [cycles, term] (None: no phase
    then) ``dt`` seconds before (None: it can)."""
    if previous is None:
        return slip_text(NO_PREVIOUS, 0.0, 0.0, config)
    if lli & 1:
        return slip_text(LOSS_OF_LOCK, dt, 0.0, config)
    if not 0.0 < dt <= config.max_gap_s:
        return slip_text(GAP, dt, 0.0, config)
    if math.isfinite(doppler_hz):
        off = cycles - previous[0] + doppler_hz * dt
        if abs(off) > config.slip_cycles_per_s * dt:
            return slip_text(SLIP, dt, off, config)
    return None


def slip_text(code: int, dt: float, off: float, config: TdcpConfig) -> str | None:
    """A row's reason from its code (None: differenced), ``off`` the cycles off the Doppler for SLIP."""
    if code == DIFFERENCED:
        return None
    if code == NO_PREVIOUS:
        return "no carrier phase at the previous epoch"
    if code == LOSS_OF_LOCK:
        return "loss of lock (lli bit 0)"
    if code == GAP:
        return f"{dt:g} s since the previous epoch (max gap {config.max_gap_s:g} s)"
    if code == SLIP:
        return f"phase change {off:+.1f} cycles off the Doppler's over {dt:g} s"
    return "no carrier phase"


def displacement(
    history: PhaseHistory,
    t: float,
    sats: Sequence[str],
    cycles: np.ndarray,
    wavelength_m: np.ndarray,
    sat_position: np.ndarray,
    terms_now: np.ndarray,
    elevation: np.ndarray,
    doppler_hz: np.ndarray,
    lli: np.ndarray,
    config: TdcpConfig,
    fit: Fit | None = None,
) -> Displacement:
    """Fit the displacement since ``history``'s epoch from the rows with finite ``cycles``; ``terms_now`` is
    :func:`model_terms` of this epoch at ``history.receiver`` (the previous position), ``elevation`` (rad)
    sets each difference's std, ``phase_std_m`` / sin(elevation) (floored at 10 deg). ``fit``: the least
    squares to run (default :func:`fit_rows`, numpy)."""
    n = len(sats)
    reasons: list[str | None] = [slip_text(NO_PHASE, 0.0, 0.0, config)] * n
    if history.receiver is None or history.t is None:
        return Displacement(None, None, 0.0, reasons, "no previous epoch with carrier phase")
    known = history.phases
    rows: list[int] = []
    before: list[tuple[float, float]] = []
    # the rows as Python numbers, read once (an element read from numpy costs more than the test)
    all_cycles, dopplers, flags = cycles.tolist(), doppler_hz.tolist(), lli.tolist()
    for row in range(n):
        value = all_cycles[row]
        if not math.isfinite(value):
            continue
        kept = known.get(sats[row])
        why = slip_reason(kept, t - history.t, value, dopplers[row], int(flags[row]), config)
        reasons[row] = why
        if kept is not None and why is None:
            rows.append(row)
            before.append(kept)
    if len(rows) < config.min_satellites:
        return too_few(rows, reasons, config)
    index = np.array(rows)
    previous = np.array(before)
    y = wavelength_m[index] * (cycles[index] - previous[:, 0]) - terms_now[index] + previous[:, 1]
    design = np.empty((len(rows), _UNKNOWNS))
    towards = sat_position[index] - np.array(history.receiver)
    design[:, :3] = towards / -np.sqrt(np.einsum("ij,ij->i", towards, towards))[:, None]
    design[:, 3] = 1.0
    std = config.phase_std_m / np.maximum(np.sin(elevation[index]), MIN_SIN_ELEVATION)
    return (fit or fit_rows)(index, y, design, std, reasons, config)


def too_few(rows: Sequence[int], reasons: list[str | None], config: TdcpConfig) -> Displacement:
    """No displacement: fewer differenced ``rows`` than the fit needs (each says so)."""
    for row in rows:
        reasons[row] = f"{len(rows)} continuous phases, fewer than {config.min_satellites}"
    return Displacement(None, None, 0.0, reasons, f"{len(rows)} continuous carrier phases")


def fit_rows(
    index: np.ndarray,
    y: np.ndarray,
    design: np.ndarray,
    std: np.ndarray,
    reasons: list[str | None],
    config: TdcpConfig,
) -> Displacement:
    """Weighted least squares of [d, clock change] with the chi-square test of its residuals; while it fails,
    the row with the largest standardised residual is left out (its reason says by how much)."""
    keep = np.arange(len(index))
    while True:
        root = 1.0 / std[keep]  # square roots of the weights
        a = design[keep] * root[:, None]
        b = y[keep] * root
        normal = a.T @ a
        try:
            cov = np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            cov = None
        if cov is None or not np.isfinite(cov).all() or _condition(normal, cov) > MAX_CONDITION:
            for r in keep.tolist():
                reasons[int(index[r])] = "the satellites' geometry does not fix a displacement"
            return Displacement(None, None, 0.0, reasons, "singular geometry")
        solution = cov @ (a.T @ b)
        weighted = b - a @ solution  # residuals over their std
        if float(weighted @ weighted) <= bound(config.gate_probability, len(keep) - _UNKNOWNS):
            for r in keep.tolist():
                reasons[int(index[r])] = None
            return Displacement(solution[:3], cov[:3, :3], float(solution[3]), reasons, None)
        leverage = np.einsum("ij,jk,ik->i", a, cov, a)
        standardised = np.abs(weighted) / np.sqrt(np.maximum(1.0 - leverage, 1e-9))
        worst = int(np.argmax(standardised))
        reasons[int(index[keep[worst]])] = (
            f"phase difference {weighted[worst] * std[keep[worst]]:+.2f} m off the displacement fit "
            f"({standardised[worst]:.1f} sigma; a slip or a reflection)"
        )
        keep = np.delete(keep, worst)
        if len(keep) < config.min_satellites:
            for r in keep.tolist():
                reasons[int(index[r])] = "the epoch's phase differences are inconsistent (chi-square test)"
            return Displacement(None, None, 0.0, reasons, "inconsistent phase differences")


def _condition(normal: np.ndarray, inverse: np.ndarray) -> float:
    """The infinity-norm condition number of ``normal``, from its inverse."""
    return float(np.abs(normal).sum(axis=1).max() * np.abs(inverse).sum(axis=1).max())


@functools.lru_cache(maxsize=256)
def bound(probability: float, dof: int) -> float:
    """The chi-square quantile, computed once per (probability, degrees of freedom): scipy's ppf costs tens
    of microseconds, a tenth of the epoch's displacement fit."""
    return float(chi2.ppf(probability, dof)) if dof > 0 else 0.0
