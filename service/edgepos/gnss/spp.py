"""Epoch-by-epoch weighted least-squares single-point positioning (the project's "plain WLS baseline").

Unknowns: ECEF position (m) and one receiver clock bias per constellation (m, i.e. c times seconds). The
measurement model is rho_sagnac + b_sys - c dt_sat + I + T; weights 1 / (a^2 + b^2 / sin^2 el); satellites
below the elevation mask are dropped once the estimate is near the Earth's surface. After convergence a
global chi-square test on the weighted residuals decides whether the satellite with the largest standardised
residual is excluded and the solution recomputed, one at a time.

When the epoch carries Doppler, :func:`solve_velocity` then solves ECEF velocity (m/s) and the receiver
clock drift (m/s) by weighted least squares on the range rates at the solved position (the model of
``core/measurements/range_rate.py``, linear in the unknowns), with the same chi-square exclusion.

``python -m edgepos.gnss.spp --obs OBS --nav NAV [--reference CSV]`` solves a recording and prints figures.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from edgepos.core.errors import EstimationError
from edgepos.gnss.geodesy import ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from edgepos.gnss.measurements import (
    DEFAULT_GALILEO_GROUP_DELAY,
    GALILEO_GROUP_DELAYS,
    Atmosphere,
    PseudorangeSet,
    prepare_epoch,
    without_group_delay,
)
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT, BroadcastOrbits, sagnac_range, sagnac_range_rate
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import (
    ALL_SYSTEMS,
    DEFAULT_CODES,
    ObservationEpoch,
    parse_systems,
    read_epochs,
    read_header,
)

_NEAR_SURFACE_M = (6.0e6, 7.0e6)
"""Geocentric distances between which the estimate counts as a ground receiver (mask and corrections on)."""


class SppError(EstimationError):
    """An epoch could not be solved (too few satellites, no convergence, singular geometry)."""


@dataclass(frozen=True)
class SppConfig:
    """Options of the WLS solver. Sigmas in metres, angles in radians."""

    elevation_mask_rad: float = math.radians(10.0)
    sigma_a_m: float = 1.0
    """Constant part of the pseudorange standard deviation."""
    sigma_b_m: float = 1.0
    """Elevation-dependent part: sigma^2 = a^2 + b^2 / sin^2(elevation)."""
    min_cn0_dbhz: float | None = None
    """Drop pseudoranges whose C/N0 is below this (None: keep all)."""
    max_iterations: int = 15
    convergence_m: float = 1e-4
    outlier_probability: float = 0.999
    """Chi-square test level of the weighted residuals; above it the worst satellite is excluded."""
    max_exclusions: int = 4
    ionosphere: bool = True
    troposphere: bool = True
    doppler_sigma_a_mps: float = 0.1
    """Range-rate standard deviation, constant part (m/s): sigma^2 = a^2 + b^2 / sin^2(elevation). a = b =
    0.1 m/s follows the Doppler residuals at the reference on the recording's first half (robust std 0.06 m/s
    above 60 deg, 0.35 m/s at 10-20 deg; docs/gnss.md)."""
    doppler_sigma_b_mps: float = 0.1
    """Range-rate standard deviation, elevation-dependent part (m/s)."""
    corrected_sigma_a_m: float = 0.0
    """Pseudoranges with a differential correction: constant part of the std (m). The fit of a^2 + b^2 /
    sin^2(el) to the corrected residuals' robust variance at the reference on the recording's first half
    (docs/gnss.md) gave a negative a^2, so 0."""
    corrected_sigma_b_m: float = 0.8
    """... and the elevation-dependent part (m): the same fit's b, 0.79 rounded."""


@dataclass(frozen=True)
class Dop:
    """Dilution of precision of the unweighted geometry (dimensionless)."""

    gdop: float
    pdop: float
    hdop: float
    vdop: float


@dataclass(frozen=True)
class VelocitySolution:
    """ECEF velocity (m/s), the same in east/north/up at the solved position, receiver clock drift (m/s, c
    times s/s), range-rate residuals (m/s) of the used satellites (``sats``) and those excluded."""

    velocity: np.ndarray
    velocity_enu: np.ndarray
    clock_drift_mps: float
    sats: tuple[str, ...]
    residuals_mps: np.ndarray
    excluded: tuple[str, ...]
    chi2_passed: bool


@dataclass(frozen=True)
class SppSolution:
    """One epoch's solution. ``residuals_m``/``elevation_rad`` are per used satellite (order of ``sats``)."""

    gpst: float
    position: np.ndarray
    lat: float
    lon: float
    height: float
    clock_bias_m: dict[str, float]
    dop: Dop
    sats: tuple[str, ...]
    residuals_m: np.ndarray
    elevation_rad: np.ndarray
    excluded: tuple[str, ...]
    iterations: int
    chi2_passed: bool
    masked: tuple[str, ...] = field(default=())
    velocity: VelocitySolution | None = None
    """From the epoch's Doppler when it has enough (else None)."""


def _weights(elevation: np.ndarray, config: SppConfig, corrected: np.ndarray | None = None) -> np.ndarray:
    sin_el = np.maximum(np.sin(elevation), 0.05)
    variance = config.sigma_a_m**2 + (config.sigma_b_m / sin_el) ** 2
    if corrected is not None:
        variance = np.where(
            corrected, config.corrected_sigma_a_m**2 + (config.corrected_sigma_b_m / sin_el) ** 2, variance
        )
    result: np.ndarray = 1.0 / variance
    return result


def _iterate(
    prs: PseudorangeSet,
    active: np.ndarray,
    atmosphere: Atmosphere,
    config: SppConfig,
    start: np.ndarray,
    differential: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, float], np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Gauss-Newton on the rows in ``active``; returns position, clocks, and per-row (all rows) residuals,
    elevations, weights, design matrix (position part), the final used mask and the iteration count."""
    x = start.astype(float).copy()
    systems = np.array(prs.systems)
    clocks: dict[str, float] = {}
    n = len(prs)
    corrected = prs.pseudorange_m + SPEED_OF_LIGHT * prs.sat_clock_s
    for iteration in range(1, config.max_iterations + 1):
        radius = float(np.linalg.norm(x))
        if _NEAR_SURFACE_M[0] < radius < _NEAR_SURFACE_M[1]:
            iono, tropo, elevation, _ = atmosphere.delays(x, prs)
            used = active & (elevation >= config.elevation_mask_rad)
        else:
            iono = tropo = np.zeros(n)
            elevation = np.full(n, np.pi / 2.0)
            used = active.copy()
        present = sorted(set(systems[used]))
        rho = sagnac_range(prs.sat_position, x)
        line_of_sight = (x - prs.sat_position) / rho[:, None]
        clock_vector = np.array([clocks.get(s, 0.0) for s in systems])
        residual = corrected - (rho + clock_vector + iono + tropo)
        if used.sum() < 3 + len(present):
            raise SppError(f"{int(used.sum())} usable pseudoranges for {3 + len(present)} unknowns")
        design = np.zeros((n, 3 + len(present)))
        design[:, :3] = line_of_sight
        for column, system in enumerate(present):
            design[systems == system, 3 + column] = 1.0
        weight = _weights(elevation, config, differential)
        root = np.sqrt(weight[used])
        step, *_ = np.linalg.lstsq(design[used] * root[:, None], residual[used] * root, rcond=None)
        if not np.all(np.isfinite(step)):
            raise SppError("non-finite least-squares step")
        x += step[:3]
        clocks = {s: clocks.get(s, 0.0) + float(step[3 + k]) for k, s in enumerate(present)}
        if np.linalg.norm(step[:3]) < config.convergence_m:
            clock_vector = np.array([clocks.get(s, 0.0) for s in systems])
            rho = sagnac_range(prs.sat_position, x)
            residual = corrected - (rho + clock_vector + iono + tropo)
            return x, clocks, residual, elevation, weight, design, used, iteration
    raise SppError(f"no convergence in {config.max_iterations} iterations")


def _dop(design: np.ndarray, position: np.ndarray) -> Dop:
    lat, lon, _ = ecef_to_geodetic(position)
    enu = design.copy()
    enu[:, :3] = design[:, :3] @ enu_rotation(float(lat), float(lon)).T
    try:
        cov = np.linalg.inv(enu.T @ enu)
    except np.linalg.LinAlgError:
        raise SppError("singular satellite geometry (no dilution of precision)") from None
    diag = np.diag(cov)
    if not (np.all(np.isfinite(cov)) and np.all(diag > 0.0)):
        raise SppError("degenerate satellite geometry (no dilution of precision)")
    return Dop(
        float(np.sqrt(np.trace(cov))),
        float(np.sqrt(diag[:3].sum())),
        float(np.sqrt(diag[:2].sum())),
        float(np.sqrt(diag[2])),
    )


def solve_epoch(
    prs: PseudorangeSet,
    atmosphere: Atmosphere,
    config: SppConfig = SppConfig(),
    initial: np.ndarray | None = None,
    corrected: np.ndarray | None = None,
) -> SppSolution:
    """Solve one epoch; ``initial`` ECEF guess (m), the Earth's centre when None; ``corrected`` (boolean per
    row) marks pseudoranges with a differential correction, weighted with ``config.corrected_sigma_*``.
    Raises SppError."""
    if not config.ionosphere or not config.troposphere:
        atmosphere = Atmosphere(atmosphere.klobuchar if config.ionosphere else None, config.troposphere)
    active = np.isfinite(prs.pseudorange_m)
    if config.min_cn0_dbhz is not None:
        active &= ~(prs.cn0_dbhz < config.min_cn0_dbhz)
    start = np.zeros(3) if initial is None else np.asarray(initial, dtype=float)
    excluded: list[int] = []
    while True:
        x, clocks, residual, elevation, weight, design, used, iterations = _iterate(
            prs, active, atmosphere, config, start, corrected
        )
        rows = np.flatnonzero(used)
        h = design[rows][:, : design.shape[1]]
        h = h[:, np.any(h != 0.0, axis=0)]
        dof = len(rows) - h.shape[1]
        normalised = residual[rows] * np.sqrt(weight[rows])
        statistic = float(normalised @ normalised)
        passed = dof <= 0 or statistic <= _chi2_quantile(config.outlier_probability, dof)
        if passed or len(excluded) >= config.max_exclusions or dof < 2:
            break
        # Standardised residuals: divide by sqrt(1 - leverage) of the weighted design.
        hw = h * np.sqrt(weight[rows])[:, None]
        leverage = np.einsum("ij,jk,ik->i", hw, np.linalg.pinv(hw.T @ hw), hw)
        standardised = np.abs(normalised) / np.sqrt(np.maximum(1.0 - leverage, 1e-6))
        worst = int(rows[np.argmax(standardised)])
        excluded.append(worst)
        active[worst] = False
        start = x
    lat, lon, height = (float(v) for v in ecef_to_geodetic(x))
    sats = prs.sats
    velocity = None
    if prs.has_doppler:
        try:
            velocity = solve_velocity(prs, x, elevation, active & used, config)
        except SppError:
            velocity = None  # too few Dopplers or a singular geometry: the position stands on its own
    return SppSolution(
        gpst=prs.gpst,
        position=x,
        lat=lat,
        lon=lon,
        height=height,
        clock_bias_m=clocks,
        dop=_dop(design[rows][:, np.any(design[rows] != 0.0, axis=0)], x),
        sats=tuple(sats[i] for i in rows),
        residuals_m=residual[rows],
        elevation_rad=elevation[rows],
        excluded=tuple(sats[i] for i in excluded),
        iterations=iterations,
        chi2_passed=passed,
        masked=tuple(sats[i] for i in np.flatnonzero(active & ~used)),
        velocity=velocity,
    )


@functools.lru_cache(maxsize=256)
def _chi2_quantile(probability: float, dof: int) -> float:
    """chi2.ppf, cached: the Doppler velocity runs every gnss_tight epoch (its zero-velocity detection), and
    scipy's quantile costs more than the solve."""
    return float(chi2.ppf(probability, dof))


def solve_velocity(
    prs: PseudorangeSet,
    position: np.ndarray,
    elevation: np.ndarray,
    usable: np.ndarray,
    config: SppConfig = SppConfig(),
) -> VelocitySolution:
    """Velocity and receiver clock drift from the range rates of the rows in ``usable`` (boolean) that have
    one, at a solved ECEF ``position`` (m) with the rows' elevations (rad). Raises SppError.

    -lambda D = u . (v_s - v) + omega_e (x_s vy - y_s vx + vx_s y - vy_s x) / c + d - c dt_s_dot is linear in
    (v, d); one weighted least-squares solve, then while the chi-square test of the weighted residuals
    fails, the row with the largest standardised residual is excluded (at most ``config.max_exclusions``).
    """
    if prs.range_rate_mps is None or prs.sat_velocity is None or prs.sat_clock_drift is None:
        raise SppError("no Doppler in this epoch")
    active = usable & np.isfinite(prs.range_rate_mps) & np.isfinite(prs.sat_clock_drift)
    zero = np.zeros(3)
    known = (
        sagnac_range_rate(prs.sat_position, prs.sat_velocity, position, zero)
        - SPEED_OF_LIGHT * prs.sat_clock_drift
    )
    diff = prs.sat_position - position
    unit = diff / np.linalg.norm(diff, axis=1)[:, None]
    design = np.zeros((len(prs), 4))
    design[:, :3] = -unit
    design[:, 0] -= OMEGA_EARTH * prs.sat_position[:, 1] / SPEED_OF_LIGHT
    design[:, 1] += OMEGA_EARTH * prs.sat_position[:, 0] / SPEED_OF_LIGHT
    design[:, 3] = 1.0
    observed = prs.range_rate_mps - known
    sin_el = np.maximum(np.sin(elevation), 0.05)
    root = 1.0 / np.sqrt(config.doppler_sigma_a_mps**2 + (config.doppler_sigma_b_mps / sin_el) ** 2)
    excluded: list[int] = []
    while True:
        rows = np.flatnonzero(active)
        dof = rows.size - 4
        if dof < 0:
            raise SppError(f"{rows.size} usable Dopplers for 4 unknowns")
        weighted = design[rows] * root[rows, None]
        # lstsq's rank (rcond None) counts the singular values above the tolerance matrix_rank uses
        solution, _, rank, _ = np.linalg.lstsq(weighted, observed[rows] * root[rows], rcond=None)
        if not np.all(np.isfinite(solution)) or rank < 4:
            raise SppError("singular Doppler geometry")
        residual = observed - design @ solution
        normalised = residual[rows] * root[rows]
        statistic = float(normalised @ normalised)
        passed = dof == 0 or statistic <= _chi2_quantile(config.outlier_probability, dof)
        if passed or len(excluded) >= config.max_exclusions or dof < 2:
            break
        leverage = np.einsum("ij,jk,ik->i", weighted, np.linalg.pinv(weighted.T @ weighted), weighted)
        standardised = np.abs(normalised) / np.sqrt(np.maximum(1.0 - leverage, 1e-6))
        worst = int(rows[np.argmax(standardised)])
        excluded.append(worst)
        active[worst] = False
    lat, lon, _ = ecef_to_geodetic(position)
    sats = prs.sats
    return VelocitySolution(
        velocity=solution[:3].copy(),
        velocity_enu=enu_rotation(float(lat), float(lon)) @ solution[:3],
        clock_drift_mps=float(solution[3]),
        sats=tuple(sats[i] for i in rows),
        residuals_mps=residual[rows],
        excluded=tuple(sats[i] for i in excluded),
        chi2_passed=passed,
    )


def solve_recording(
    obs_path: str,
    nav_path: str,
    config: SppConfig = SppConfig(),
    codes: Mapping[str, tuple[str, str]] | None = None,
    galileo_group_delay: str = DEFAULT_GALILEO_GROUP_DELAY,
) -> list[tuple[float, SppSolution | None, str]]:
    """Solve every epoch of a RINEX observation file: (GPS time, solution or None, reason when None). The
    receiver's Galileo clocks follow ``galileo_group_delay`` (``gnss.measurements``).

    Each epoch starts from the previous solution (the header's approximate position, else the Earth's
    centre, for the first); a failed epoch restarts from there, so one bad epoch cannot poison the next.
    """
    nav = read_navigation(nav_path)
    orbits = BroadcastOrbits(nav.ephemerides)
    atmosphere = Atmosphere.from_navigation(nav)
    header = read_header(obs_path)
    fallback = np.asarray(header.approx_position, float) if header.approx_position else np.zeros(3)
    if not np.all(np.isfinite(fallback)) or np.linalg.norm(fallback) < 1.0:
        fallback = np.zeros(3)
    previous: np.ndarray | None = None
    results: list[tuple[float, SppSolution | None, str]] = []
    no_group_delay = without_group_delay(galileo_group_delay)
    for epoch in read_epochs(obs_path, codes):
        prs, _ = prepare_epoch(epoch, orbits, codes, no_group_delay)
        try:
            solution = solve_epoch(prs, atmosphere, config, previous if previous is not None else fallback)
        except SppError as error:
            results.append((epoch.gpst, None, str(error)))
            continue
        previous = solution.position
        results.append((epoch.gpst, solution, ""))
    return results


def read_reference(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Reference CSV (GPS week, seconds of week, latitude deg, longitude deg, height m, ...; ``#`` comments)
    -> (GPS seconds (n,), ECEF positions (n, 3))."""
    data = np.loadtxt(path, delimiter=",", comments="#", ndmin=2)
    if data.shape[1] < 5:
        raise ValueError(
            f"{path}: expected at least 5 columns (week, sow, lat, lon, height), got {data.shape[1]}"
        )
    gpst = data[:, 0] * 604800.0 + data[:, 1]
    return gpst, geodetic_to_ecef(np.radians(data[:, 2]), np.radians(data[:, 3]), data[:, 4])


def reference_velocity(ref_time: np.ndarray, ref_ecef: np.ndarray, max_gap_s: float = 1.5) -> np.ndarray:
    """ECEF velocity (m/s) per reference epoch by the central difference of its neighbours' positions (exact
    for constant acceleration); NaN at the ends and where a neighbour is more than ``max_gap_s`` away."""
    velocity = np.full_like(ref_ecef, np.nan, dtype=float)
    if len(ref_time) < 3:
        return velocity
    before, after = ref_time[1:-1] - ref_time[:-2], ref_time[2:] - ref_time[1:-1]
    ok = (before <= max_gap_s) & (after <= max_gap_s) & (before > 0.0) & (after > 0.0)
    span = (ref_time[2:] - ref_time[:-2])[:, None]
    inner = (ref_ecef[2:] - ref_ecef[:-2]) / span
    velocity[1:-1] = np.where(ok[:, None], inner, np.nan)
    return velocity


def horizontal_errors(
    solutions: Iterable[tuple[float, SppSolution | None, str]],
    ref_time: np.ndarray,
    ref_ecef: np.ndarray,
    tolerance_s: float = 0.05,
) -> tuple[np.ndarray, int, int]:
    """Horizontal errors (m) of solved epochs that have a reference within ``tolerance_s``; also the number of
    reference epochs and how many of them have no solution."""
    errors: list[float] = []
    by_time = {round(t, 1): s for t, s, _ in solutions}
    unsolved = 0
    for t, truth in zip(ref_time, ref_ecef):
        solution = by_time.get(round(float(t), 1))
        if solution is None or abs(solution.gpst - t) > tolerance_s:
            unsolved += 1
            continue
        lat, lon, _ = ecef_to_geodetic(truth)
        enu = enu_rotation(float(lat), float(lon)) @ (solution.position - truth)
        errors.append(float(np.hypot(enu[0], enu[1])))
    return np.asarray(errors), len(ref_time), unsolved


def summary(errors: np.ndarray) -> dict[str, float]:
    """RMS, 95th percentile and maximum (m) of horizontal errors."""
    if errors.size == 0:
        return {"horizontal_rms_m": math.nan, "horizontal_p95_m": math.nan, "horizontal_max_m": math.nan}
    return {
        "horizontal_rms_m": float(np.sqrt(np.mean(errors**2))),
        "horizontal_p95_m": float(np.percentile(errors, 95)),
        "horizontal_max_m": float(errors.max()),
    }


def epochs_at_reference(
    obs_path: str, codes: Mapping[str, tuple[str, str]], ref_time: np.ndarray, first: int, stop: int
) -> Iterator[tuple[ObservationEpoch, int]]:
    """Epochs ``first..stop-1`` of a recording that have a reference row within 0.05 s, each with that
    row's index: what the residual analyses at the reference walk."""
    for number, epoch in enumerate(read_epochs(obs_path, codes)):
        if number >= stop:
            break
        if number < first:
            continue
        row = int(np.argmin(np.abs(ref_time - epoch.gpst)))
        if abs(ref_time[row] - epoch.gpst) <= 0.05:
            yield epoch, row


def add_galileo_group_delay_argument(parser: argparse.ArgumentParser) -> None:
    """``--galileo-group-delay``: the receiver's Galileo convention (``gnss.measurements``)."""
    parser.add_argument(
        "--galileo-group-delay",
        choices=GALILEO_GROUP_DELAYS,
        default=DEFAULT_GALILEO_GROUP_DELAY,
        help="what the receiver's Galileo code carries of the satellite group delay (gnss_tight's "
        f"galileo_group_delay; default {DEFAULT_GALILEO_GROUP_DELAY})",
    )


def residual_tool_inputs(args: argparse.Namespace) -> tuple[str, str, str, int, int, str]:
    """The recording, reference, epoch range and constellations of a :func:`residual_tool_parser` line."""
    first, stop = epoch_range(args.epochs)
    return args.obs, args.nav, args.reference, first, stop, args.systems


def residual_tool_parser(prog: str, description: str) -> argparse.ArgumentParser:
    """The command line the residual analyses at the reference share (``gnss.doppler_residuals``,
    ``gnss.pseudorange_noise``): the recording, its reference, a range of epochs and the constellations."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--obs", required=True, help="RINEX 3 observation file")
    parser.add_argument("--nav", required=True, help="RINEX 3 navigation file")
    parser.add_argument(
        "--reference", required=True, help="reference CSV: week, seconds of week, lat, lon, height"
    )
    parser.add_argument("--epochs", default="0:1000000", help="epochs A:B (0-based, B excluded)")
    parser.add_argument("--systems", default=ALL_SYSTEMS, help=f"constellations (default {ALL_SYSTEMS})")
    add_galileo_group_delay_argument(parser)
    return parser


def epoch_range(text: str) -> tuple[int, int]:
    """``A:B`` of ``--epochs`` as (first, stop)."""
    first, stop = (int(v) for v in text.split(":"))
    return first, stop


def main(argv: Sequence[str] | None = None) -> int:
    """Solve a recording; with ``--reference`` print horizontal RMS / p95 against it."""
    parser = argparse.ArgumentParser(prog="python -m edgepos.gnss.spp", description=__doc__.splitlines()[0])
    parser.add_argument("--obs", required=True, help="RINEX 3 observation file")
    parser.add_argument("--nav", required=True, help="RINEX 3 navigation file (GPS/BeiDou/Galileo)")
    parser.add_argument(
        "--reference", help="reference CSV: week, seconds of week, lat deg, lon deg, height m"
    )
    parser.add_argument(
        "--systems",
        default=ALL_SYSTEMS,
        help=f"constellations to use (default {ALL_SYSTEMS}, all this project reads; e.g. GC)",
    )
    parser.add_argument("--mask-deg", type=float, default=10.0, help="elevation mask (degrees)")
    add_galileo_group_delay_argument(parser)
    parser.add_argument(
        "--max-exclusions",
        type=int,
        default=SppConfig.max_exclusions,
        help="outliers excluded per epoch at most (0: plain WLS without exclusion)",
    )
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    try:
        codes = {s: DEFAULT_CODES[s] for s in parse_systems(args.systems)}
    except ValueError as error:
        parser.error(str(error))
    config = SppConfig(elevation_mask_rad=math.radians(args.mask_deg), max_exclusions=args.max_exclusions)
    results = solve_recording(args.obs, args.nav, config, codes, args.galileo_group_delay)
    report: dict[str, object] = {"epochs": len(results), "fixes": sum(s is not None for _, s, _ in results)}
    if args.reference:
        ref_time, ref_ecef = read_reference(args.reference)
        errors, count, unsolved = horizontal_errors(results, ref_time, ref_ecef)
        report.update({"reference_epochs": count, "reference_epochs_unsolved": unsolved, **summary(errors)})
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key}: {value:.2f}" if isinstance(value, float) else f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
