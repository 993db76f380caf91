"""``edgepos eval gnss-rinex``: the gnss_tight pipeline on a real recording (RINEX 3 observation and
navigation files) against a reference trajectory, beside the project's epoch-by-epoch WLS baseline.

GNSS-only (a recording has no inertial data). Each epoch's pseudoranges become ``pseudorange``
observations (GPS time of week, system, PRN, pseudorange, C/N0 and the Doppler of the same signal, no
satellite states) and go through
``GnssTightPipeline.process`` one epoch per batch with the ephemerides in its environment and the state
serialised in between: the same code path as ``POST /v1/sessions/{id}/batches``.
Reference CSV: GPS week, seconds of week, latitude (deg), longitude (deg), ellipsoidal height (m), ...
(``#`` comments), as in tests/data/gnss-rover/README.md. Velocity is scored against the reference's central
differences (``spp.reference_velocity``): the horizontal error of the fix's (vx, vy), east and north of the
site frame, against the reference's east and north velocity at its own position (the two frames differ by
the few kilometres' rotation, 1e-3 rad: 0.01 m/s at 10 m/s). ``--score-epochs A:B`` scores only epochs
A..B-1 (0-based) of one run from the first epoch, so halves of a recording are scored on the same run.

Integrity (eval/gnss_integrity.py): per scored epoch with a reference, the fix's error against its
protection level and state (misleading, hazardous, availability, detections, median protection level) and
the NEES of its covariance, raw and as the monitor inflates it; ``--plots DIR`` draws the Stanford diagram.

``--base BASE.rnx`` adds differential corrections from a reference station's observations
(gnss/differential.py) at its known position (``--base-position X,Y,Z`` ECEF m, else the file header's
APPROX POSITION XYZ plus its antenna delta): the pipeline gets them in its environment, as the service
would, and the WLS baseline adds the same corrections (with the same rules: same satellite and ephemeris
issue, newest base epoch at or before, ``--max-correction-age``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgepos.cli_output import prepare_output, write_output
from edgepos.eval.gnss_integrity import GnssIntegrity, error_en, integrity_lines
from edgepos.eval.overrides import add_option_argument, parse_overrides
from edgepos.gnss.differential import DEFAULT_MAX_AGE_S, correct_set, corrections_from_epochs
from edgepos.gnss.differential import base_position as header_base_position
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.geodesy import ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from edgepos.gnss.measurements import (
    GALILEO_GROUP_DELAYS,
    STATION_GALILEO_GROUP_DELAY,
    prepare_epoch,
    without_group_delay,
)
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import ALL_SYSTEMS, DEFAULT_CODES, parse_systems, read_epochs, read_header
from edgepos.gnss.spp import SppConfig, SppError, read_reference, reference_velocity, solve_epoch
from edgepos.pipelines.base import Fix, StaticEnvironment
from edgepos.pipelines.gnss_recording import epoch_pseudoranges
from edgepos.pipelines.gnss_tight import GnssTightPipeline


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--obs", required=True, help="RINEX 3 observation file")
    parser.add_argument("--nav", required=True, help="RINEX 3 navigation file (GPS / BeiDou / Galileo)")
    parser.add_argument(
        "--reference", required=True, help="reference CSV: week, seconds of week, lat deg, lon deg, height m"
    )
    parser.add_argument("--json", metavar="FILE", default=None, help="also write the figures as JSON to FILE")
    parser.add_argument(
        "--systems",
        type=_systems,
        default=ALL_SYSTEMS,
        help=f"constellations to use (default {ALL_SYSTEMS}: GPS, BeiDou and Galileo, all this project reads; GC: without "
        "Galileo)",
    )
    parser.add_argument("--filter", default="upf", choices=("upf", "pf", "ukf"), help="filter (default upf)")
    parser.add_argument("--particles", type=int, default=200, help="particles of pf / upf (default 200)")
    parser.add_argument(
        "--no-fuzzy", action="store_true", help="constant pseudorange noise instead of the fuzzy factor"
    )
    parser.add_argument("--seed", type=int, default=1, help="the filter's random seed (default 1)")
    parser.add_argument("--max-epochs", type=int, default=None, help="stop after this many epochs")
    parser.add_argument(
        "--score-epochs",
        type=_epoch_range,
        default=None,
        metavar="A:B",
        help="score only epochs A..B-1 (0-based; the run still starts at epoch 0), e.g. 0:150 and 150:300",
    )
    parser.add_argument(
        "--base",
        metavar="BASE.rnx",
        default=None,
        help="RINEX 3 observations of a reference station: differential corrections",
    )
    parser.add_argument(
        "--max-correction-age",
        type=float,
        default=DEFAULT_MAX_AGE_S,
        metavar="S",
        help=f"with --base: corrections older than S seconds are not applied (default {DEFAULT_MAX_AGE_S:g}; "
        "see docs/gnss.md)",
    )
    parser.add_argument(
        "--base-galileo-group-delay",
        choices=GALILEO_GROUP_DELAYS,
        default=STATION_GALILEO_GROUP_DELAY,
        help="what the station receiver's Galileo code carries of the satellite group delay (the vehicle's: "
        f"--option galileo_group_delay=...; default {STATION_GALILEO_GROUP_DELAY}, as a registered station's)",
    )
    parser.add_argument(
        "--base-position",
        type=_position,
        default=None,
        metavar="X,Y,Z",
        help="the reference station's ECEF antenna position (m; default: from --base's header)",
    )
    parser.add_argument(
        "--carrier",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="send each pseudorange's carrier phase (the L observation of its signal, cycles) and loss-of-lock "
        "indicator from the RINEX as carrier_cycles / lli, as a client sends what its receiver records (the "
        "pipeline's carrier_smoothing option says what it does with them; default: sent; --no-carrier sends "
        "code and Doppler only)",
    )
    parser.add_argument(
        "--plots",
        metavar="DIR",
        default=None,
        help="write a Stanford diagram (error against protection level) of the run to DIR",
    )
    add_option_argument(parser, "pseudorange_std=3")


def _systems(text: str) -> str:
    try:
        return parse_systems(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _position(text: str) -> tuple[float, float, float]:
    """``X,Y,Z`` (ECEF m, on the Earth's surface) -> a tuple."""
    try:
        x, y, z = (float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z (three ECEF metres), got {text!r}") from None
    if not all(math.isfinite(v) for v in (x, y, z)) or not 6.0e6 < math.hypot(x, y, z) < 7.0e6:
        raise argparse.ArgumentTypeError(f"{text!r} is not an ECEF position on the Earth's surface")
    return x, y, z


def _epoch_range(text: str) -> tuple[int, int]:
    """``A:B`` -> (A, B) with 0 <= A < B."""
    try:
        first, stop = (int(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A:B (epoch indices), got {text!r}") from None
    if not 0 <= first < stop:
        raise argparse.ArgumentTypeError(f"need 0 <= A < B, got {text!r}")
    return first, stop


def _score(
    times: Sequence[float],
    positions: Sequence[np.ndarray | None],
    reference: tuple[np.ndarray, np.ndarray],
    epochs: int,
    velocities: Sequence[np.ndarray | None] | None = None,
) -> dict[str, Any]:
    """Horizontal position errors (m) at the reference epochs among ``times``; with ``velocities`` (east,
    north m/s per epoch, None without one) also their horizontal errors against the reference velocity."""
    ref_time, ref_ecef = reference
    ref_velocity = reference_velocity(ref_time, ref_ecef)
    first, last = (min(times), max(times)) if times else (math.inf, -math.inf)
    by_time = {round(t, 1): k for k, t in enumerate(times)}
    errors = []
    velocity_errors = []
    missing = reference_epochs = 0
    for t, truth, truth_velocity in zip(ref_time, ref_ecef, ref_velocity):
        if not first - 0.05 <= t <= last + 0.05:
            continue
        reference_epochs += 1
        k = by_time.get(round(float(t), 1))
        position = None if k is None else positions[k]
        if position is None:
            missing += 1
            continue
        lat, lon, _ = ecef_to_geodetic(truth)
        rotation = enu_rotation(float(lat), float(lon))
        enu = rotation @ (position - truth)
        errors.append(math.hypot(enu[0], enu[1]))
        velocity = None if velocities is None or k is None else velocities[k]
        if velocity is not None and np.all(np.isfinite(truth_velocity)):
            truth_enu = rotation @ truth_velocity
            velocity_errors.append(math.hypot(velocity[0] - truth_enu[0], velocity[1] - truth_enu[1]))
    values = np.asarray(errors)
    empty = values.size == 0
    report: dict[str, Any] = {
        "epochs": epochs,
        "fixes": sum(p is not None for p in positions),
        "reference_epochs": reference_epochs,
        "reference_epochs_without_fix": missing,
        "horizontal_rms_m": None if empty else float(np.sqrt(np.mean(values**2))),
        "horizontal_p95_m": None if empty else float(np.percentile(values, 95)),
        "horizontal_max_m": None if empty else float(values.max()),
    }
    if velocities is not None:
        speeds = np.asarray(velocity_errors)
        none = speeds.size == 0
        report["velocity_epochs"] = int(speeds.size)
        report["velocity_rms_mps"] = None if none else float(np.sqrt(np.mean(speeds**2)))
        report["velocity_p95_mps"] = None if none else float(np.percentile(speeds, 95))
    return report


def evaluate(
    obs_path: str,
    nav_path: str,
    reference_path: str,
    systems: str = ALL_SYSTEMS,
    options: Mapping[str, Any] | None = None,
    max_epochs: int | None = None,
    score_epochs: tuple[int, int] | None = None,
    base_path: str | None = None,
    base_position: Sequence[float] | None = None,
    max_correction_age_s: float = DEFAULT_MAX_AGE_S,
    carrier: bool = False,
    plots: str | None = None,
    base_galileo_group_delay: str = STATION_GALILEO_GROUP_DELAY,
) -> dict[str, Any]:
    """Run the pipeline and the WLS baseline over a recording; the figures as a dict (of epochs
    ``score_epochs`` = (A, B), A..B-1, when given; the run then stops after epoch B-1). With ``base_path``
    both use differential corrections from that reference station. With ``carrier`` the pseudoranges carry
    their carrier phase and loss-of-lock indicator (the WLS baseline does not use them)."""
    if score_epochs is not None:
        max_epochs = score_epochs[1] if max_epochs is None else min(max_epochs, score_epochs[1])
    codes = {s: DEFAULT_CODES[s] for s in parse_systems(systems)}
    navigation = read_navigation(nav_path)
    ephemerides = Ephemerides.from_navigation(navigation)
    pipeline = GnssTightPipeline()
    resolved = pipeline.resolve_options({"systems": sorted(codes), **(options or {})})
    table = None
    if base_path is not None:
        station = (
            header_base_position(read_header(base_path))
            if base_position is None
            else np.asarray(base_position, float)
        )
        table = corrections_from_epochs(
            read_epochs(base_path, codes),
            station,
            ephemerides.orbits,
            ephemerides.atmosphere,
            codes,
            resolved["elevation_mask"],
            max_correction_age_s,
            without_group_delay(base_galileo_group_delay),
        )
    environment = StaticEnvironment(navigation=ephemerides, differential=table)
    use_doppler = bool(resolved["use_doppler"])
    state = pipeline.create(resolved, None)
    reference = read_reference(reference_path)
    atmosphere = ephemerides.atmosphere
    config = SppConfig()

    times: list[float] = []
    fixes: list[np.ndarray | None] = []
    fix_velocities: list[np.ndarray | None] = []
    fix_objects: list[Fix | None] = []
    baseline: list[np.ndarray | None] = []
    baseline_velocities: list[np.ndarray | None] = []
    previous: np.ndarray | None = None
    pipeline_seconds = 0.0
    for count, epoch in enumerate(read_epochs(obs_path, codes)):
        if max_epochs is not None and count >= max_epochs:
            break
        batch = epoch_pseudoranges(epoch, carrier=carrier)
        started = time.perf_counter()
        epoch_fixes, state = pipeline.process(state, batch, environment)
        pipeline_seconds += time.perf_counter() - started
        times.append(epoch.gpst)
        fix = epoch_fixes[0] if epoch_fixes else None
        fix_objects.append(fix)
        if fix is None or fix.latitude is None or fix.longitude is None or fix.height is None:
            fixes.append(None)
        else:
            fixes.append(geodetic_to_ecef(fix.latitude, fix.longitude, fix.height))
        if fix is not None and fix.vx is not None and fix.vy is not None:
            fix_velocities.append(np.array([fix.vx, fix.vy]))
        else:
            fix_velocities.append(None)
        prs, _ = prepare_epoch(
            epoch, ephemerides.orbits, codes, without_group_delay(resolved["galileo_group_delay"])
        )
        corrected = None
        if table is not None:
            prs, corrected, _ = correct_set(
                prs, ephemerides.orbits, table, table.max_age_s, systems=resolved["correction_systems"]
            )
        if not use_doppler:
            prs = dataclasses.replace(prs, range_rate_mps=None, sat_velocity=None, sat_clock_drift=None)
        try:
            solution = solve_epoch(prs, atmosphere, config, previous, corrected)
            previous = solution.position
            baseline.append(solution.position)
            baseline_velocities.append(
                None if solution.velocity is None else solution.velocity.velocity_enu[:2]
            )
        except SppError:
            baseline.append(None)
            baseline_velocities.append(None)
    if score_epochs is not None:
        keep = slice(score_epochs[0], score_epochs[1])
        times, fixes, fix_velocities = times[keep], fixes[keep], fix_velocities[keep]
        fix_objects = fix_objects[keep]
        baseline, baseline_velocities = baseline[keep], baseline_velocities[keep]
    report = _score(times, fixes, reference, len(times), fix_velocities)
    report["integrity"] = _integrity(times, fixes, fix_objects, reference).summary(
        resolved["alert_limit_m"], resolved["integrity_inflation"]
    )
    if plots is not None:
        title = f"gnss_tight {resolved['filter']}" + (" + base" if base_path is not None else "")
        name = (
            f"stanford-gnss-rinex-{resolved['filter']}" + ("-base" if base_path is not None else "") + ".png"
        )
        report["integrity"]["stanford_plot"] = str(
            _integrity(times, fixes, fix_objects, reference).stanford_plot(
                resolved["alert_limit_m"], title, Path(plots) / name
            )
        )
    report["filter"] = resolved["filter"]
    report["particles"] = resolved["particles"] if resolved["filter"] != "ukf" else 1
    report["fuzzy"] = resolved["fuzzy"]
    report["noise_model"] = resolved["noise_model"]
    report["systems"] = systems
    report["seconds_per_epoch"] = pipeline_seconds / max(len(times), 1)
    report["use_doppler"] = use_doppler
    report["carrier_sent"] = carrier
    report["carrier_smoothing"] = resolved["carrier_smoothing"]
    report["score_epochs"] = None if score_epochs is None else list(score_epochs)
    report["base"] = (
        None
        if base_path is None
        else {
            "file": base_path,
            "position_ecef_m": [float(v) for v in station],
            "corrections": len(table or ()),
        }
    )
    report["baseline"] = {
        "method": "epoch-by-epoch WLS (gnss/spp.py)",
        **_score(times, baseline, reference, len(times), baseline_velocities if use_doppler else None),
    }
    return report


def _integrity(
    times: Sequence[float],
    positions: Sequence[np.ndarray | None],
    fixes: Sequence[Fix | None],
    reference: tuple[np.ndarray, np.ndarray],
) -> GnssIntegrity:
    """The integrity tally of the fixes at the reference epochs (as ``_score`` matches them)."""
    ref_time, ref_ecef = reference
    truth = {round(float(t), 1): p for t, p in zip(ref_time, ref_ecef)}
    tally = GnssIntegrity()
    for t, position, fix in zip(times, positions, fixes, strict=True):
        true = truth.get(round(t, 1))
        if true is None or position is None or fix is None or fix.position_cov is None:
            continue
        lat, lon, _ = ecef_to_geodetic(true)
        tally.add(error_en(position, true, enu_rotation(float(lat), float(lon))), fix)
    return tally


def _format(value: Any) -> str:
    return "-" if value is None else (f"{value:.2f}" if isinstance(value, float) else str(value))


def run(args: argparse.Namespace) -> int:
    options: dict[str, Any] = {
        "filter": args.filter,
        "particles": args.particles,
        "fuzzy": not args.no_fuzzy,
        "seed": args.seed,
    }
    if args.base_position is not None and args.base is None:
        print(
            "edgepos eval gnss-rinex: error: --base-position needs --base (the station's observations)",
            file=sys.stderr,
        )
        return 2
    if args.base_galileo_group_delay != STATION_GALILEO_GROUP_DELAY and args.base is None:
        print("edgepos eval gnss-rinex: error: --base-galileo-group-delay needs --base", file=sys.stderr)
        return 2
    if args.max_correction_age != DEFAULT_MAX_AGE_S and args.base is None:
        print("edgepos eval gnss-rinex: error: --max-correction-age needs --base", file=sys.stderr)
        return 2
    if args.json and (problem := prepare_output(args.json)) is not None:
        print(f"edgepos eval gnss-rinex: error: --json: {problem}", file=sys.stderr)
        return 2
    try:
        options.update(parse_overrides(args.option))
        GnssTightPipeline().resolve_options(options)
    except ValueError as error:  # a malformed --option, or one the pipeline refuses (PipelineInputError)
        print(f"edgepos eval gnss-rinex: error: {error}", file=sys.stderr)
        return 2
    try:
        report = evaluate(
            args.obs,
            args.nav,
            args.reference,
            args.systems,
            options,
            args.max_epochs,
            args.score_epochs,
            args.base,
            args.base_position,
            args.max_correction_age,
            args.carrier,
            args.plots,
            args.base_galileo_group_delay,
        )
    except (OSError, ValueError) as error:  # unreadable or malformed files (RinexError is a ValueError)
        print(f"edgepos eval gnss-rinex: error: {error}", file=sys.stderr)
        return 2
    details = [f"{report['particles']} particles"] if report["filter"] != "ukf" else []
    if report["noise_model"] == "fitted":
        details += ["fitted noise"]
    else:
        details += ["fuzzy"] if report["fuzzy"] else []
    label = f"gnss_tight {report['filter']}" + (f" ({', '.join(details)})" if details else "")
    label += " + Doppler" if report["use_doppler"] else " no Doppler"
    label += " + base" if report["base"] is not None else ""
    if report["carrier_sent"]:
        label += " + carrier" if report["carrier_smoothing"] != "off" else " (carrier unused)"
    if report["score_epochs"] is not None:
        print(f"scored epochs {report['score_epochs'][0]}..{report['score_epochs'][1] - 1}")
    print(
        f"{'solution':<48} {'epochs':>6} {'fixes':>6} {'ref w/o fix':>11} {'RMS m':>7} {'p95 m':>7} {'max m':>7} "
        f"{'vel RMS m/s':>11}"
    )
    baseline_label = "WLS baseline (gnss/spp.py)" + (" + base" if report["base"] is not None else "")
    for name, row in ((label, report), (baseline_label, report["baseline"])):
        print(
            f"{name:<48} {row['epochs']:>6} {row['fixes']:>6} {row['reference_epochs_without_fix']:>11} "
            f"{_format(row['horizontal_rms_m']):>7} {_format(row['horizontal_p95_m']):>7} {_format(row['horizontal_max_m']):>7} "
            f"{_format(row.get('velocity_rms_mps')):>11}"
        )
    print(f"pipeline time per epoch: {1e3 * report['seconds_per_epoch']:.1f} ms")
    for line in integrity_lines(report["integrity"]):
        print(line)
    if args.json:
        write_output(args.json, json.dumps(report, indent=2))
    return 0
