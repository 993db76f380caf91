"""The GNSS + RISS Monte Carlo: every algorithm of Jiang & Chen's Table 2 on the same simulated runs.

Run r draws its measurements from ``np.random.default_rng([seed, r])`` (the scenario, city and
constellation are fixed). Each algorithm is a set of ``gnss_tight`` pipeline options; its session is
created and fed exactly as the service does it: one batch per GNSS epoch (that second's RISS samples and
the epoch's pseudoranges with ``sat_position``/``sat_clock``), the state bytes carried between batches,
the site origin in the environment. A batch the pipeline raises on is counted and skipped with the
previous state kept, as the service would (it answers an error and stores nothing). The particle
filters' own seed is drawn from [seed, r, 1], the same for every algorithm. Errors are horizontal
(east, north) at the GNSS epochs, in the site frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from edgepos.core.observations import Observation, PseudorangeObservation
from edgepos.eval import montecarlo
from edgepos.eval.gnss_ramp import Ramp, inject
from edgepos.eval.gnss_ramp import tally as ramp_tally
from edgepos.eval.progress import Progress
from edgepos.gnss.geodesy import ecef_to_enu, geodetic_to_ecef
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet
from edgepos.gnss.spp import SppConfig, solve_epoch
from edgepos.pipelines.base import Fix, Pipeline, StaticEnvironment
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.gnss_scenario import SCENARIOS, GnssScenario
from edgepos.sim.gnss_sensors import FREQUENCY_HZ, GnssRun, simulate

PIPELINE = "gnss_tight"
#: The non-pipeline baseline: the project's single-epoch least squares on the same pseudoranges.
WLS = "WLS"


@dataclass(frozen=True)
class PaperRow:
    """A column of the paper's Table 2: horizontal maximum and RMS error (m)."""

    max_m: float
    rms_m: float


@dataclass(frozen=True)
class Algorithm:
    name: str
    options: dict[str, Any]
    uses_particles: bool
    paper: PaperRow | None
    description: str


PAPER_MEASUREMENTS = {"noise_model": "fuzzy", "carrier_smoothing": "off", "use_doppler": False}
"""The paper's measurement model: pseudoranges alone (no carrier phase, no Doppler), with the equal (eq. 19)
or fuzzy (eq. 20) noise; the service's defaults since issue 16 (noise fitted on the real recording,
carrier-smoothed code, Doppler) would make every paper row the same model."""

#: The algorithms compared: the paper's PF and improved UPF, the UPF without the fuzzy logic (the
#: ablation between them), the single UKF baseline with and without the fuzzy logic (all on the
#: paper's measurement model), the UPF as a session opens it by default (the service's noise model and
#: the carrier phase and Doppler), and the project's least squares without any filter.
ALGORITHMS: dict[str, Algorithm] = {
    a.name: a
    for a in (
        Algorithm(
            "PF",
            {"filter": "pf", "fuzzy": False, **PAPER_MEASUREMENTS},
            True,
            PaperRow(12.32, 4.34),
            "particle filter, prior as proposal, equal pseudorange noise (eq. 19)",
        ),
        Algorithm(
            "UPF",
            {"filter": "upf", "fuzzy": False, **PAPER_MEASUREMENTS},
            True,
            None,
            "unscented particle filter, equal pseudorange noise",
        ),
        Algorithm(
            "UPF+fuzzy",
            {"filter": "upf", "fuzzy": True, **PAPER_MEASUREMENTS},
            True,
            PaperRow(8.69, 3.39),
            "the paper's improved UPF: fuzzy noise from elevation and C/N0 (eq. 20)",
        ),
        Algorithm(
            "UKF",
            {"filter": "ukf", "fuzzy": True, **PAPER_MEASUREMENTS},
            False,
            None,
            "a single UKF with fuzzy noise (the cheap baseline)",
        ),
        Algorithm(
            "UKF-equal",
            {"filter": "ukf", "fuzzy": False, **PAPER_MEASUREMENTS},
            False,
            None,
            "the same UKF with equal pseudorange noise: what the fuzzy logic alone is worth",
        ),
        Algorithm(
            "UPF-default",
            {"filter": "upf"},
            True,
            None,
            "the UPF with the service's defaults: noise fitted on the real recording, carrier-smoothed code, "
            "Doppler",
        ),
        Algorithm(
            WLS,
            {},
            False,
            None,
            "epoch-by-epoch weighted least squares (gnss/spp.py), no filter: the plain baseline",
        ),
    )
}


class UnknownAlgorithm(ValueError):
    """An --algorithms entry that names no known algorithm."""


def select_algorithms(spec: str | None) -> list[Algorithm]:
    """Algorithms named in a comma-separated ``spec`` (case-insensitive) in table order; all for None."""
    if spec is None:
        return list(ALGORITHMS.values())
    folded = {name.casefold(): name for name in ALGORITHMS}
    items = [item.strip() for item in spec.split(",") if item.strip()]
    unknown = [item for item in items if item.casefold() not in folded]
    if unknown or not items:
        raise UnknownAlgorithm(
            f"--algorithms: unknown or no algorithm {unknown or spec!r}; known: {', '.join(ALGORITHMS)}"
        )
    wanted = {folded[item.casefold()] for item in items}
    return [algorithm for name, algorithm in ALGORITHMS.items() if name in wanted]


@dataclass
class Sums:
    """One algorithm over some runs: per-epoch sums of squared horizontal error and fix counts, each
    run's maximum and RMS, epochs without a fix, excluded pseudoranges and processing time."""

    error_sq: np.ndarray  # (K,)
    fixes: np.ndarray  # (K,) runs with a position fix at epoch k
    run_max: list[float]
    run_rms: list[float]
    excluded: int
    pseudoranges: int
    seconds: float
    epochs: int
    failures: list[str]
    """Batches the pipeline raised on (run, time, error): the service would answer 500 and keep the
    session's previous state, so the run goes on from there and those epochs have no fix."""
    integrity: np.ndarray | None = None
    """The pipeline's integrity counts (eval/gnss_ramp.py); None for the WLS baseline."""

    def __add__(self, other: Sums) -> Sums:
        return Sums(
            self.error_sq + other.error_sq,
            self.fixes + other.fixes,
            self.run_max + other.run_max,
            self.run_rms + other.run_rms,
            self.excluded + other.excluded,
            self.pseudoranges + other.pseudoranges,
            self.seconds + other.seconds,
            self.epochs + other.epochs,
            self.failures + other.failures,
            None if self.integrity is None or other.integrity is None else self.integrity + other.integrity,
        )


@dataclass
class Totals:
    runs: int
    sums: dict[str, Sums] = field(default_factory=dict)
    los: float = 0.0
    nlos: float = 0.0
    track: dict[str, np.ndarray] | None = None
    """Run 0's true and estimated east/north tracks (for the figures)."""


def combine(first: Totals, second: Totals) -> Totals:
    """Totals of two disjoint sets of runs, ``first`` before ``second``."""
    sums = {name: first.sums[name] + second.sums[name] for name in first.sums}
    track = first.track if first.track is not None else second.track
    return Totals(first.runs + second.runs, sums, first.los + second.los, first.nlos + second.nlos, track)


class RunFailed(RuntimeError):
    """A filter could not process one run; names the algorithm and run."""


@dataclass
class _Context:
    seed: int
    scenario: GnssScenario
    pipeline: Pipeline
    environment: StaticEnvironment
    algorithms: list[tuple[str, dict[str, Any]]]
    ramp: Ramp | None = None


_CONTEXT: _Context | None = None


def build_scenario(name: str, short: bool) -> GnssScenario:
    return SCENARIOS[name](short=short)


def _init_worker(
    names: tuple[str, ...],
    seed: int,
    scenario: str,
    short: bool,
    particles: int,
    overrides: dict[str, Any] | None = None,
    ramp: Ramp | None = None,
) -> None:
    global _CONTEXT
    built = build_scenario(scenario, short)
    pipeline = get_pipeline(PIPELINE)
    algorithms: list[tuple[str, dict[str, Any]]] = []
    for name in names:
        if name == WLS:
            algorithms.append((name, {}))
            continue
        options = {
            **ALGORITHMS[name].options,
            "particles": particles,
            "gps_week": built.gps_week,
            **(overrides or {}),
        }
        algorithms.append((name, pipeline.resolve_options(options)))
    environment = StaticEnvironment(origin=built.site)
    _CONTEXT = _Context(seed, built, pipeline, environment, algorithms, ramp)


def batches(run: GnssRun, every: int) -> list[list[Observation]]:
    """One batch per GNSS epoch: the RISS samples since the previous one, then this epoch's
    observations (its RISS sample and pseudoranges), as a vehicle reporting once a second sends them."""
    out: list[list[Observation]] = []
    pending: list[Observation] = []
    for index, epoch in enumerate(run.epochs):
        pending.extend(epoch)
        if index % every == 0:
            out.append(pending)
            pending = []
    if pending:
        out.append(pending)
    return out


def _run_chunk(chunk: range) -> Totals:
    context = _CONTEXT
    assert context is not None, "worker not initialised"
    scenario = context.scenario
    totals: Totals | None = None
    for run_index in chunk:
        run = simulate(scenario, np.random.default_rng([context.seed, run_index]))
        filter_seed = int(np.random.default_rng([context.seed, run_index, 1]).integers(2**62))
        epoch_of = {round(float(t), 6): k for k, t in enumerate(run.gnss_tow)}
        count = run.gnss_tow.size
        run_batches = batches(run, scenario.gnss_every)
        victim: str | None = None
        start: float | None = None
        if context.ramp is not None:  # the pipeline's batches only: the WLS baseline sees the clean run
            run_batches, victim, start = inject(run_batches, context.ramp)
        sums: dict[str, Sums] = {}
        track: dict[str, np.ndarray] = {"truth": np.stack([run.truth_east, run.truth_north], axis=-1)}
        for name, options in context.algorithms:
            started = time.perf_counter()
            located: list[tuple[int, Fix, frozenset[str]]] = []
            if name == WLS:
                outcome = _least_squares(context, run)
            else:
                outcome = _pipeline(context, options, filter_seed, run_batches, epoch_of, count, located)
            estimates, excluded, pseudoranges, failures = outcome
            seconds = time.perf_counter() - started
            error = np.hypot(estimates[:, 0] - run.truth_east, estimates[:, 1] - run.truth_north)
            have = np.isfinite(error)
            if not have.any():
                detail = f" ({failures[0]})" if failures else ""
                raise RunFailed(
                    f"{name} gave no position fix in run {run_index} (seed {context.seed}){detail}"
                )
            sums[name] = Sums(
                np.where(have, error, 0.0) ** 2,
                have.astype(int),
                [float(np.max(error[have]))],
                [float(np.sqrt(np.mean(error[have] ** 2)))],
                excluded,
                pseudoranges,
                seconds,
                count,
                [f"run {run_index} {message}" for message in failures],
                None
                if name == WLS
                else ramp_tally(
                    [(fix, screened) for _, fix, screened in located],
                    [float(error[k]) for k, _, _ in located],
                    options["alert_limit_m"],
                    victim,
                    start,
                ),
            )
            track[name] = estimates
        run_totals = Totals(
            1,
            sums,
            float(run.los.sum(axis=1).mean()),
            float(run.nlos.sum(axis=1).mean()),
            track if run_index == 0 else None,
        )
        totals = run_totals if totals is None else combine(totals, run_totals)
    assert totals is not None
    return totals


def _pipeline(
    context: _Context,
    options: dict[str, Any],
    filter_seed: int,
    run_batches: list[list[Observation]],
    epoch_of: dict[float, int],
    count: int,
    located: list[tuple[int, Fix, frozenset[str]]] | None = None,
) -> tuple[np.ndarray, int, int, list[str]]:
    """One session of the pipeline over the run's batches: (east, north) per GNSS epoch (NaN without a
    fix), pseudoranges not used, pseudoranges reported, failed batches."""
    state = context.pipeline.create({**options, "seed": filter_seed}, None)
    estimates = np.full((count, 2), np.nan)
    excluded = pseudoranges = 0
    failures: list[str] = []
    for batch in run_batches:
        try:
            fixes, state = context.pipeline.process(state, batch, context.environment)
        except Exception as exc:  # noqa: BLE001 - the service would answer 500 and keep the state
            failures.append(f"t={batch[-1].t}: {type(exc).__name__}: {exc}")
            continue
        for fix in fixes:
            k = epoch_of.get(round(fix.t, 6))
            if k is not None and fix.x is not None and fix.y is not None:
                estimates[k] = (fix.x, fix.y)
                if located is not None:
                    located.append((k, fix, screened(fix, batch)))
            for use in fix.measurements:
                if use.kind == "pseudorange":
                    pseudoranges += 1
                    excluded += not use.used
    return estimates, excluded, pseudoranges, failures


def screened(fix: Fix, batch: list[Observation]) -> frozenset[str]:
    """The satellites (e.g. G05) whose pseudorange a fault screen of the pipeline or its integrity monitor
    left out of this fix (not those below the mask or C/N0 floor)."""
    out = set()
    for use in fix.measurements:
        observation = batch[use.index]
        if use.used or use.reason is None or not isinstance(observation, PseudorangeObservation):
            continue
        if use.reason.startswith(("excluded", "failed the residual test")):
            out.add(f"{observation.system}{observation.prn:02d}")
    return frozenset(out)


def _least_squares(context: _Context, run: GnssRun) -> tuple[np.ndarray, int, int, list[str]]:
    """The project's epoch-by-epoch WLS (gnss/spp.py, default settings) on the same pseudoranges, each
    epoch started from the previous solution (the first from the Earth's centre, as the pipeline does)."""
    scenario = context.scenario
    origin = geodetic_to_ecef(*scenario.site)
    estimates = np.full((run.gnss_tow.size, 2), np.nan)
    excluded = pseudoranges = 0
    failures: list[str] = []
    previous = None
    gnss_epochs = (epoch for epoch in run.epochs if any(o.kind == "pseudorange" for o in epoch))
    for k, epoch in enumerate(gnss_epochs):
        observed = [o for o in epoch if isinstance(o, PseudorangeObservation)]
        prs = PseudorangeSet(
            scenario.gps_week * 604800.0 + observed[0].t,
            tuple(o.system for o in observed),
            np.array([o.prn for o in observed]),
            np.array([o.pseudorange for o in observed]),
            np.array([o.cn0 for o in observed]),
            np.array([o.sat_position for o in observed], dtype=float),
            np.array([o.sat_clock for o in observed], dtype=float),
            np.array([FREQUENCY_HZ[o.system] for o in observed]),
        )
        pseudoranges += len(prs)
        try:
            solution = solve_epoch(prs, Atmosphere(None, True), SppConfig(), previous)
        except Exception as exc:  # noqa: BLE001 - counted like a failed pipeline batch
            failures.append(f"t={observed[0].t}: {type(exc).__name__}: {exc}")
            excluded += len(prs)
            continue
        previous = solution.position
        excluded += len(prs) - len(solution.sats)
        estimates[k] = ecef_to_enu(solution.position, origin)[:2]
    return estimates, excluded, pseudoranges, failures


def monte_carlo(
    algorithms: list[Algorithm],
    runs: int,
    seed: int,
    workers: int,
    scenario: str,
    short: bool,
    particles: int,
    progress: Progress | None = None,
    overrides: dict[str, Any] | None = None,
    ramp: Ramp | None = None,
) -> Totals:
    """Totals over ``runs`` runs, identical for any ``workers`` (times aside); ``overrides``: pipeline
    options set for every filter on top of each algorithm's own (``--option``)."""
    names = tuple(algorithm.name for algorithm in algorithms)
    return montecarlo.run_chunks(
        _run_chunk,
        combine,
        montecarlo.chunk_runs(runs),
        workers,
        _init_worker,
        (names, seed, scenario, short, particles, dict(overrides or {}), ramp),
        progress,
    )


@dataclass(frozen=True)
class Result:
    """One algorithm's figures over all runs."""

    algorithm: Algorithm
    rms_m: float
    """Horizontal RMS over every epoch of every run."""
    max_m: float
    """Largest horizontal error of any run."""
    mean_run_max_m: float
    """The per-run maximum averaged over runs (one drive's max, as the paper's)."""
    curve: np.ndarray
    """(K,) RMS over runs at each GNSS epoch."""
    missing: int
    """Epochs (over all runs) without a position fix."""
    excluded_share: float
    epoch_ms: float
    failures: list[str]


def results(algorithms: list[Algorithm], totals: Totals) -> dict[str, Result]:
    out = {}
    for algorithm in algorithms:
        sums = totals.sums[algorithm.name]
        fixes = int(sums.fixes.sum())
        curve = np.sqrt(sums.error_sq / np.maximum(sums.fixes, 1))
        out[algorithm.name] = Result(
            algorithm,
            float(np.sqrt(sums.error_sq.sum() / fixes)),
            float(max(sums.run_max)),
            float(np.mean(sums.run_max)),
            np.where(sums.fixes > 0, curve, np.nan),
            int(sums.fixes.size * totals.runs - fixes),
            sums.excluded / max(sums.pseudoranges, 1),
            sums.seconds / sums.epochs * 1e3,
            sums.failures,
        )
    return out
