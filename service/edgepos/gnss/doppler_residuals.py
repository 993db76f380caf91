"""Doppler residuals at a reference trajectory: how noisy a recording's range rates are, by elevation and C/N0.

At each epoch with a reference velocity (central differences of the reference positions), the residual of
every Doppler above the elevation mask is -lambda D minus the modelled range rate (satellite velocity and
clock drift, Sagnac rate; ``orbits.sagnac_range_rate``) at the reference position and velocity, with the
epoch's median removed (the receiver clock drift is common to all satellites). Reported: RMS, robust std
(1.4826 x median absolute residual) and percentiles, per elevation and C/N0 band, and the same divided by the
fuzzy noise factor (``core.fuzzy``) the gnss_tight pipeline scales a Doppler's std with. This is what chose
the pipeline's ``doppler_std_mps`` and the baseline's Doppler weights on the first half of the recording:

``python -m edgepos.gnss.doppler_residuals --obs OBS --nav NAV --reference CSV --epochs 0:150``
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence

import numpy as np

from edgepos.core.fuzzy import FuzzyNoise
from edgepos.gnss.geodesy import elevation_azimuth
from edgepos.gnss.measurements import prepare_epoch
from edgepos.gnss.orbits import SPEED_OF_LIGHT, BroadcastOrbits, sagnac_range_rate
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import ALL_SYSTEMS, DEFAULT_CODES
from edgepos.gnss.spp import (
    epoch_range,
    epochs_at_reference,
    read_reference,
    reference_velocity,
    residual_tool_parser,
)


def residuals(
    obs_path: str,
    nav_path: str,
    reference_path: str,
    first: int,
    stop: int,
    systems: str = ALL_SYSTEMS,
    mask_rad: float = math.radians(10.0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Median-centred Doppler residuals (m/s) of epochs first..stop-1, with their elevations (rad) and C/N0."""
    codes = {s: DEFAULT_CODES[s] for s in systems if s in DEFAULT_CODES}
    orbits = BroadcastOrbits(read_navigation(nav_path).ephemerides)
    ref_time, ref_ecef = read_reference(reference_path)
    ref_velocity = reference_velocity(ref_time, ref_ecef)
    values: list[np.ndarray] = []
    elevations: list[np.ndarray] = []
    cn0s: list[np.ndarray] = []
    for epoch, row in epochs_at_reference(obs_path, codes, ref_time, first, stop):
        if not np.all(np.isfinite(ref_velocity[row])):
            continue
        prs, _ = prepare_epoch(epoch, orbits, codes)
        if prs.range_rate_mps is None or prs.sat_velocity is None or prs.sat_clock_drift is None:
            continue
        elevation, _ = elevation_azimuth(ref_ecef[row], prs.sat_position)
        modelled = sagnac_range_rate(prs.sat_position, prs.sat_velocity, ref_ecef[row], ref_velocity[row])
        residual = prs.range_rate_mps - modelled + SPEED_OF_LIGHT * prs.sat_clock_drift
        keep = np.isfinite(residual) & (elevation >= mask_rad)
        if keep.sum() < 3:
            continue
        values.append(residual[keep] - np.median(residual[keep]))
        elevations.append(elevation[keep])
        cn0s.append(prs.cn0_dbhz[keep])
    if not values:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return np.concatenate(values), np.concatenate(elevations), np.concatenate(cn0s)


def _line(label: str, values: np.ndarray) -> str:
    if values.size == 0:
        return f"{label}: none"
    robust = 1.4826 * float(np.median(np.abs(values)))
    rms = float(np.sqrt(np.mean(values**2)))
    p95 = float(np.percentile(np.abs(values), 95))
    return f"{label}: n={values.size} RMS {rms:.3f} robust std {robust:.3f} p95 |r| {p95:.3f} max {np.abs(values).max():.2f}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = residual_tool_parser("python -m edgepos.gnss.doppler_residuals", __doc__.splitlines()[0])
    args = parser.parse_args(argv)
    first, stop = epoch_range(args.epochs)
    values, elevation, cn0 = residuals(args.obs, args.nav, args.reference, first, stop, args.systems)
    print(_line(f"epochs {first}..{stop - 1}, residual m/s", values))
    degrees = np.degrees(elevation)
    for low, high in ((10, 20), (20, 35), (35, 60), (60, 90)):
        print(_line(f"  elevation {low}-{high} deg", values[(degrees >= low) & (degrees < high)]))
    for low, high in ((0, 35), (35, 42), (42, 48), (48, 100)):
        print(_line(f"  C/N0 {low}-{high} dB-Hz", values[(cn0 >= low) & (cn0 < high)]))
    factor = FuzzyNoise().factor(elevation, cn0) if values.size else np.zeros(0)
    print(_line("divided by the fuzzy factor, m/s", values / factor if values.size else values))
    return 0


if __name__ == "__main__":
    sys.exit(main())
