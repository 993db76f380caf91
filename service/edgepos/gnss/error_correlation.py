"""Time-correlated pseudorange errors: the variance formulas for a first-order Gauss-Markov (AR(1)) error,
and the measurement of its correlation time on a recording with a reference trajectory. Pure numpy.

Model: a pseudorange's error is e_k = w_k + m_k, a white part w (variance (1 - a) sigma^2) and a
Gauss-Markov part m (variance a sigma^2, correlation rho = exp(-dt / tau) between epochs dt apart), sigma the
noise model's std (gnss/pseudorange_noise.py). Two consequences a filter that treats e as white gets wrong:

* the mean of n consecutive errors (what the Hatch filter's smoothed code carries, gnss/carrier.py) has
  variance sigma^2 [(1 - a) / n + a V(n, rho)], V(n, rho) = (1/n) [1 + 2 sum_{k=1}^{n-1} (1 - k/n) rho^k],
  not sigma^2 / n: only n (1 - rho) / (1 + rho) of the samples are effectively independent;
* a filter that averages many epochs sees the error's long-run variance (its spectral density at zero
  frequency), sigma^2 [(1 - a) + a (1 + rho) / (1 - rho)], not sigma^2. A low-pass filter with unit gain at
  zero frequency (the Hatch filter) leaves that long-run variance unchanged: smoothed code gives a filter of
  long memory no more information than raw code.

``python -m edgepos.gnss.error_correlation --obs OBS --nav NAV --reference CSV --epochs 0:150`` prints the
pooled autocorrelation of the standardised pseudorange residuals at the reference position (raw code, and
Hatch-smoothed code when the recording has carrier phase), the Gauss-Markov fit (tau, a), and the smoothed
code's measured variance against the white rule 1/n and the correlated rule above: what chose the defaults
of ``code_error_tau_s`` and ``code_error_correlated_fraction`` (docs/gnss.md).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.gnss.carrier import CarrierTrack, HatchConfig, hatch_update
from edgepos.gnss.measurements import (
    DEFAULT_GALILEO_GROUP_DELAY,
    Atmosphere,
    prepare_epoch,
    without_group_delay,
)
from edgepos.gnss.orbits import SPEED_OF_LIGHT, BroadcastOrbits, sagnac_range
from edgepos.gnss.pseudorange_noise import FITTED
from edgepos.gnss.rinex_nav import read_navigation
from edgepos.gnss.rinex_obs import DEFAULT_CODES
from edgepos.gnss.spp import (
    epoch_range,
    epochs_at_reference,
    read_reference,
    residual_tool_inputs,
    residual_tool_parser,
)


def correlation(dt: float | np.ndarray, tau: float) -> np.ndarray:
    """rho = exp(-dt / tau) of a Gauss-Markov error between samples dt apart (0 when tau is 0: white)."""
    dt = np.asarray(dt, dtype=float)
    if tau <= 0.0:
        return np.zeros_like(dt)
    value: np.ndarray = np.exp(-np.maximum(dt, 0.0) / tau)
    return value


def mean_variance(n: float | np.ndarray, rho: float | np.ndarray) -> np.ndarray:
    """V(n, rho): the variance of the mean of n consecutive unit-variance AR(1) samples with lag-one
    correlation rho, (1/n) [1 + 2 sum_{k=1}^{n-1} (1 - k/n) rho^k], in closed form
    (1/n) [1 + 2 rho / (1 - rho) - 2 rho (1 - rho^n) / (n (1 - rho)^2)]; 1/n for rho = 0, 1 for rho = 1.
    Non-integer n (the Hatch filter's count capped by its window) is used as is."""
    count = np.maximum(np.asarray(n, dtype=float), 1.0)
    lag_one = np.minimum(np.asarray(rho, dtype=float), 1.0)
    eps = (1.0 - lag_one) + 0.0 * count  # broadcast to both shapes
    count = count + 0.0 * eps
    # near rho = 1 the closed form subtracts two numbers of order 1/(1 - rho): its first-order expansion
    # in eps = 1 - rho, 1 - eps (n^2 - 1) / (3 n), is exact to (n eps)^2 there
    exact = count * eps >= 1e-4
    e = np.where(exact, eps, 1.0)
    r = 1.0 - e
    closed = (1.0 + 2.0 * r / e - 2.0 * r * (1.0 - r**count) / (count * e**2)) / count
    out = np.where(exact, closed, 1.0 - eps * (count**2 - 1.0) / (3.0 * count))
    value: np.ndarray = np.minimum(np.maximum(out, 0.0), 1.0)
    return value


def long_run_factor(rho: float | np.ndarray) -> np.ndarray:
    """(1 + rho) / (1 - rho): an AR(1) error's long-run variance over its variance."""
    r = np.minimum(np.asarray(rho, dtype=float), 1.0 - 1e-9)
    value: np.ndarray = (1.0 + r) / (1.0 - r)
    return value


@dataclass(frozen=True)
class ErrorCorrelation:
    """The Gauss-Markov part of a pseudorange error: correlation time ``tau_s`` (s; 0: white) and the
    fraction ``fraction`` of the error variance it holds (the rest white)."""

    tau_s: float
    fraction: float

    def smoothed_variance(self, n: np.ndarray, dt: float | np.ndarray) -> np.ndarray:
        """Variance of the mean of n errors dt apart, over one error's variance (the Hatch factor squared)."""
        n = np.maximum(np.asarray(n, dtype=float), 1.0)
        correlated = mean_variance(n, correlation(dt, self.tau_s))
        value: np.ndarray = (1.0 - self.fraction) / n + self.fraction * correlated
        return value

    def long_run(self, dt: float | np.ndarray) -> np.ndarray:
        """Long-run variance over the error's variance at sampling interval dt: what a filter of long
        memory sees, (1 - a) + a (1 + rho) / (1 - rho)."""
        value: np.ndarray = (1.0 - self.fraction) + self.fraction * long_run_factor(
            correlation(dt, self.tau_s)
        )
        return value


def averaged_variance(
    count: np.ndarray, memory: float, model: ErrorCorrelation, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per row, over one raw error's variance: (the variance of its error as a filter of memory M averages
    it, times M; its own variance). For a row smoothed over n epochs (``count``; below 1: raw code, n = 1)
    the error has a white part, variance share (1 - a) / n, and a Gauss-Markov part, share a V(n, rho)
    (their sum, V_smoothed(n), is its own variance); their running means overlap by (n - 1) / n between
    epochs, so lag-one correlations r = 1 - 1/n and max(rho, 1 - 1/n); the first value is
    sum_i s_i M V(M, r_i)."""
    n = np.maximum(np.asarray(count, dtype=float), 1.0)
    rho = float(correlation(dt, model.tau_s))
    overlap = 1.0 - 1.0 / n
    gm = model.fraction * mean_variance(n, rho)
    white = (1.0 - model.fraction) / n
    spread = mean_variance(memory, np.concatenate([overlap, np.maximum(rho, overlap)]))
    averaged: np.ndarray = memory * (white * spread[: n.size] + gm * spread[n.size :])
    return averaged, white + gm


def honest_factor(
    jacobian: np.ndarray,
    variance: np.ndarray,
    prior_horizontal: np.ndarray,
    true_variance: Callable[[float], np.ndarray],
) -> tuple[float, float, np.ndarray] | None:
    """(factor, memory, the epoch's own horizontal covariance A) of a filter's epoch, None when the rows
    alone do not fix the position (no more rows than unknowns).

    memory: about how many epochs the filter averages, M = 1 + tr(P_meas) / tr(P_prior), horizontal, P_meas
    the epoch's own weighted least-squares covariance (``jacobian`` n x (3 + clocks) by north, east, up and
    the clocks, weights 1/``variance``) and P_prior the prediction's north-east covariance (a steady-state
    filter's information is the measurement's times M).

    factor: how much larger the horizontal error of that weighted solution is when the rows' errors have
    variances ``true_variance(M)``: tr(G R G') / tr(A), A = (H'WH)^-1, G = A H'W, horizontal rows (the
    consider, or sandwich, covariance of an estimator whose weights are not the errors')."""
    rows, unknowns = jacobian.shape
    prior_trace = float(np.trace(prior_horizontal))
    if rows <= unknowns or prior_trace <= 0.0:
        return None
    weighted = jacobian / variance[:, None]
    try:
        a = np.linalg.inv(jacobian.T @ weighted)
    except np.linalg.LinAlgError:
        return None
    own = float(a[0, 0] + a[1, 1])
    if not math.isfinite(own) or own <= 0.0:
        return None
    memory = 1.0 + own / prior_trace
    gain = a[:2] @ weighted.T
    true = float(np.sum(gain * gain * true_variance(memory)))
    horizontal: np.ndarray = a[:2, :2]
    return true / own, memory, horizontal


FITTED_CORRELATION = ErrorCorrelation(tau_s=56.0, fraction=0.57)
"""Fitted on epochs 0-149 of tests/data/gnss-rover (2703 standardised raw-code residuals of 22 satellites,
GPS C1C, BeiDou C2I, Galileo C1C above 10 deg, Galileo clocks as the pipeline's default
``galileo_group_delay``; the command in the module docstring): the pooled ACF about zero is 0.93 at 1 s, 0.48
at 10 s, 0.30 at 30 s, 0.26 at 60 s (never below the fit's 0.2 floor, so all 60 lags are fitted): tau 56.3 s,
a 0.57. The second half gives 58.8 s and 0.62. (Before the Galileo group delay was settled: 58.2 s and 0.57,
second half 57.7 s and 0.62; docs/gnss.md.)"""


# -- measurement on a recording -------------------------------------------------------------------


def residual_series(
    obs_path: str,
    nav_path: str,
    reference_path: str,
    first: int,
    stop: int,
    systems: str,
    mask_rad: float = math.radians(10.0),
    window_s: float = 100.0,
    galileo_group_delay: str = DEFAULT_GALILEO_GROUP_DELAY,
) -> tuple[dict[str, dict[int, float]], dict[str, dict[int, tuple[float, float]]]]:
    """Per satellite, {epoch number: standardised raw-code residual} and {epoch number: (standardised
    smoothed-code residual, epochs averaged)} at the reference position (residual / the fitted noise std,
    each epoch's per-system median removed, as gnss/pseudorange_noise.py); the smoothed series is empty
    without carrier phase."""
    codes = {s: DEFAULT_CODES[s] for s in systems if s in DEFAULT_CODES}
    navigation = read_navigation(nav_path)
    orbits = BroadcastOrbits(navigation.ephemerides)
    atmosphere = Atmosphere.from_navigation(navigation)
    ref_time, ref_ecef = read_reference(reference_path)
    tracks: dict[str, CarrierTrack] = {}
    config = HatchConfig(window_s=window_s)
    raw: dict[str, dict[int, float]] = {}
    smoothed: dict[str, dict[int, tuple[float, float]]] = {}
    for number, (epoch, row) in enumerate(epochs_at_reference(obs_path, codes, ref_time, first, stop)):
        prs, _ = prepare_epoch(epoch, orbits, codes, without_group_delay(galileo_group_delay))
        if not len(prs):
            continue
        by_sat = {sat: k for k, sat in enumerate(epoch.sats)}
        rows = [by_sat[s] for s in prs.sats]
        carrier = epoch.carrier_cycles[rows]
        hatch = hatch_update(
            tracks,
            epoch.gpst,
            prs.sats,
            prs.pseudorange_m,
            carrier,
            SPEED_OF_LIGHT / prs.frequency_hz,
            epoch.doppler_hz[rows],
            epoch.lli[rows],
            config,
        )
        iono, tropo, elevation, _ = atmosphere.delays(ref_ecef[row], prs)
        model = (
            sagnac_range(prs.sat_position, ref_ecef[row]) + iono + tropo - SPEED_OF_LIGHT * prs.sat_clock_s
        )
        std = FITTED.std(elevation, prs.cn0_dbhz)
        systems_of = np.array(prs.systems)
        for values, smoothed_rows in (
            (prs.pseudorange_m - model, False),
            (hatch.pseudorange_m - model, True),
        ):
            for system in set(prs.systems):
                keep = (systems_of == system) & np.isfinite(values) & (elevation >= mask_rad)
                if smoothed_rows:
                    keep &= hatch.count >= 1.0
                if keep.sum() < 3:
                    continue
                centred = (values[keep] - np.median(values[keep])) / std[keep]
                for k, value in zip(np.flatnonzero(keep), centred):
                    sat = prs.sats[k]
                    if smoothed_rows:
                        smoothed.setdefault(sat, {})[number] = (float(value), float(hatch.count[k]))
                    else:
                        raw.setdefault(sat, {})[number] = float(value)
    return raw, smoothed


def pooled_acf(series: dict[str, dict[int, float]], lags: Sequence[int]) -> np.ndarray:
    """Autocorrelation about zero pooled over satellites: sum r_t r_{t+L} / sqrt(sum r_t^2 sum r_{t+L}^2)
    over the pairs present (a satellite's mean over its pass counts as the slowest part of its error)."""
    out = []
    for lag in lags:
        a: list[float] = []
        b: list[float] = []
        for values in series.values():
            for t, v in values.items():
                w = values.get(t + lag)
                if w is not None:
                    a.append(v)
                    b.append(w)
        x, y = np.array(a), np.array(b)
        out.append(float(x @ y / math.sqrt((x @ x) * (y @ y))) if x.size else math.nan)
    return np.array(out)


def fit_gauss_markov(acf: np.ndarray, lags: Sequence[int], floor: float = 0.2) -> ErrorCorrelation:
    """tau and a from log ACF = log(a) - lag / tau, least squares over the lags before the ACF first
    drops below ``floor`` (at least three)."""
    lag = np.asarray(lags, dtype=float)
    below = np.flatnonzero(~(acf >= floor))
    end = max(int(below[0]) if below.size else len(acf), 3)
    slope, intercept = np.polyfit(lag[:end], np.log(np.maximum(acf[:end], 1e-3)), 1)
    return ErrorCorrelation(-1.0 / slope if slope < 0.0 else math.inf, min(math.exp(intercept), 1.0))


def main(argv: Sequence[str] | None = None) -> int:
    parser = residual_tool_parser("python -m edgepos.gnss.error_correlation", __doc__.splitlines()[0])
    args = parser.parse_args(argv)
    first, stop = epoch_range(args.epochs)
    raw, smoothed = residual_series(*residual_tool_inputs(args), galileo_group_delay=args.galileo_group_delay)
    lags = list(range(1, 61))
    acf = pooled_acf(raw, lags)
    fit = fit_gauss_markov(acf, lags)
    count = sum(len(v) for v in raw.values())
    mean_square = float(np.mean(np.array([v for s in raw.values() for v in s.values()]) ** 2))
    print(
        f"epochs {first}..{stop - 1}: {count} raw-code residuals of {len(raw)} satellites, standardised by "
        f"the fitted noise model: mean square {mean_square:.2f}"
    )
    print("lag s: " + "  ".join(f"{lag}:{acf[lag - 1]:.2f}" for lag in (1, 2, 5, 10, 20, 30, 45, 60)))
    print(f"Gauss-Markov fit: tau = {fit.tau_s:.1f} s, correlated fraction a = {fit.fraction:.2f}")
    print(f"long-run variance factor at 1 s: {float(fit.long_run(1.0)):.1f}")
    if smoothed:
        values = np.array([v for s in smoothed.values() for v, _ in s.values()])
        counts = np.array([n for s in smoothed.values() for _, n in s.values()])
        print("smoothed code: epochs averaged  count  variance / raw  white 1/n  correlated rule")
        for low, high in ((1, 2), (2, 5), (5, 10), (10, 20), (20, 40), (40, 70), (70, 101)):
            member = (counts >= low) & (counts < high)
            if member.sum() < 20:
                continue
            n = float(np.median(counts[member]))
            ratio = float(np.mean(values[member] ** 2)) / mean_square
            rule = float(fit.smoothed_variance(np.array([n]), 1.0)[0])
            print(
                f"{low:>3}-{high - 1:<3} (median {n:5.1f})  {int(member.sum()):5d}  {ratio:14.3f}  {1 / n:9.3f}  {rule:15.3f}"
            )
        smooth_acf = pooled_acf({s: {t: v for t, (v, _) in d.items()} for s, d in smoothed.items()}, lags)
        print(
            "smoothed ACF: "
            + "  ".join(f"{lag}:{smooth_acf[lag - 1]:.2f}" for lag in (1, 2, 5, 10, 20, 30, 45, 60))
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
