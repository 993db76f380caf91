"""Measure how GNSS fix errors are correlated in time, and how much of them two receivers share.

Solves the real rover recording (tests/data/gnss-rover) epoch by epoch with the project's WLS
(``edgepos.gnss.spp``, default configuration) and takes the east/north errors against the reference
trajectory; solves the reference station 14.4 km away the same way against its surveyed antenna
position. Prints per axis: the error's RMS, its autocorrelation at lags 1-60 s, the Gauss-Markov
time constant fitted to it (least squares of log ACF = -lag / tau over the lags where the ACF is
above 0.2) and the white part (the variance the exponential's extrapolation to lag 0 leaves
unexplained), and the correlation between the rover's and the station's errors at the same epoch
(the part of the error common to receivers near each other). These choose the defaults of the
``gnss_bias_tau``/``gnss_bias_std`` options of ``v2v_coop`` and ``v2x_federated`` (docs/v2v.md).

    python bench/gnss_fix_errors.py [--json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from edgepos.gnss.differential import base_position
from edgepos.gnss.geodesy import ecef_to_geodetic, enu_rotation
from edgepos.gnss.rinex_obs import read_header
from edgepos.gnss.spp import read_reference, solve_recording

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "gnss-rover"


def _enu_errors(solutions, truth_at) -> dict[int, np.ndarray]:
    """{whole GPS second: (east, north) error (m)} for the solved epochs that have a truth."""
    out = {}
    for t, solution, _ in solutions:
        truth = truth_at(t)
        if solution is None or truth is None:
            continue
        lat, lon, _ = ecef_to_geodetic(truth)
        out[round(t)] = (enu_rotation(float(lat), float(lon)) @ (solution.position - truth))[:2]
    return out


def autocorrelation(
    series: dict[int, np.ndarray], axis: int, lags: range, centred: bool = True
) -> np.ndarray:
    """ACF of one axis at whole-second lags, over the pairs both present (gaps skipped): about the mean
    (``centred``) or about zero (the error's mean counts as the slowest part of a bias)."""
    values = {t: float(e[axis]) for t, e in series.items()}
    mean = float(np.mean(list(values.values()))) if centred else 0.0
    var = float(np.mean([(v - mean) ** 2 for v in values.values()]))
    acf = []
    for lag in lags:
        pairs = [(values[t] - mean) * (values[t + lag] - mean) for t in values if t + lag in values]
        acf.append(float(np.mean(pairs)) / var if pairs else math.nan)
    return np.array(acf)


def fit_gauss_markov(acf: np.ndarray, lags: range, floor: float = 0.2) -> tuple[float, float]:
    """(tau s, fraction of the variance that is Gauss-Markov) from log ACF = log(a) - lag / tau over the
    lags until the ACF first drops below ``floor``; 1 - a is the white part."""
    lag = np.array(lags, dtype=float)
    end = int(np.argmax(acf < floor)) if np.any(acf < floor) else len(acf)
    end = max(end, 3)
    slope, intercept = np.polyfit(lag[:end], np.log(np.maximum(acf[:end], 1e-3)), 1)
    return -1.0 / slope, min(math.exp(intercept), 1.0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    nav = str(DATA / "broadcast-nav.rnx")
    ref_time, ref_ecef = read_reference(str(DATA / "reference-0-5min.csv"))
    reference = {round(float(t)): p for t, p in zip(ref_time, ref_ecef)}
    rover = _enu_errors(
        solve_recording(str(DATA / "rover-0-5min.rnx"), nav), lambda t: reference.get(round(t))
    )
    station_obs = str(DATA / "base-0-5min.rnx")
    station_at = base_position(read_header(station_obs))
    station = _enu_errors(solve_recording(station_obs, nav), lambda t: station_at)
    lags = range(1, 61)
    report: dict[str, object] = {"rover_epochs": len(rover), "station_epochs": len(station)}
    for axis, name in enumerate(("east", "north")):
        for label, series in (("rover", rover), ("station", station)):
            errors = np.array([e[axis] for e in series.values()])
            acf = autocorrelation(series, axis, lags)
            tau, markov = fit_gauss_markov(acf, lags)
            raw = autocorrelation(series, axis, lags, centred=False)
            raw_tau, raw_markov = fit_gauss_markov(raw, lags)
            report[f"{label}_{name}"] = {
                "rms_m": float(np.sqrt(np.mean(errors**2))),
                "mean_m": float(errors.mean()),
                "std_m": float(errors.std()),
                "acf_1_5_10_20_30_60": [round(float(acf[k - 1]), 3) for k in (1, 5, 10, 20, 30, 60)],
                "gm_tau_s": tau,
                "gm_fraction": markov,
                "about_zero_acf_1_5_10_20_30_60": [
                    round(float(raw[k - 1]), 3) for k in (1, 5, 10, 20, 30, 60)
                ],
                "about_zero_gm_tau_s": raw_tau,
                "about_zero_gm_fraction": raw_markov,
            }
        common = [t for t in rover if t in station]
        a = np.array([rover[t][axis] for t in common])
        b = np.array([station[t][axis] for t in common])
        report[f"rover_station_correlation_{name}"] = float(np.corrcoef(a, b)[0, 1])
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
