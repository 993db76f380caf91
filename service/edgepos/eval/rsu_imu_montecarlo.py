"""The RSU + IMU Monte Carlo: every algorithm on the same simulated runs, RMSE per time step.

Run r draws its measurements from ``np.random.default_rng([seed, r])`` and every filter starts at the
scenario's true initial state. The RMSE follows eqs. 39-40: at each time step k the RMSE over runs of
x and of y, combined as sqrt(RMSE_x^2 + RMSE_y^2) (velocity likewise); the "mean RMSE" is its
average over k = 1..K. Workers return sums, so the parent only adds and takes square roots.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from edgepos.eval import montecarlo
from edgepos.eval.integrity import IntegrityTally, tally
from edgepos.eval.progress import Progress
from edgepos.eval.rsu_imu_algorithms import Algorithm
from edgepos.eval.rsu_imu_late import LateSettings, late_columns
from edgepos.pipelines.base import Environment, InitialState, Pipeline
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.faults import RsuFaults, inject
from edgepos.sim.scenarios import Scenario, rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs

PIPELINE = "rsu_imu"


@dataclass
class Sums:
    """One algorithm's totals over some runs: per-step squared errors and model probabilities, and
    processing time."""

    pos_sq: np.ndarray  # (K,) sum over runs of (x - x_true)^2 + (y - y_true)^2
    vel_sq: np.ndarray  # (K,) the same for (vx, vy)
    probabilities: np.ndarray | None  # (K, models) for banks of several models
    seconds: float
    epochs: int
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # rsu_imu_late's columns, same shape
    integrity: IntegrityTally = field(default_factory=IntegrityTally)

    def __add__(self, other: Sums) -> Sums:
        probabilities = None
        if self.probabilities is not None and other.probabilities is not None:
            probabilities = self.probabilities + other.probabilities
        return Sums(
            self.pos_sq + other.pos_sq,
            self.vel_sq + other.vel_sq,
            probabilities,
            self.seconds + other.seconds,
            self.epochs + other.epochs,
            {name: values + other.extra[name] for name, values in self.extra.items()},
            self.integrity + other.integrity,
        )


@dataclass
class Totals:
    """Sums per algorithm over ``runs`` Monte Carlo runs."""

    runs: int
    sums: dict[str, Sums] = field(default_factory=dict)


def combine(first: Totals, second: Totals) -> Totals:
    """Totals of two disjoint sets of runs (``first`` + ``second``, in that order)."""
    sums = {name: first.sums[name] + second.sums[name] for name in first.sums}
    return Totals(first.runs + second.runs, sums)


class RunFailed(RuntimeError):
    """A filter could not process one run; names the algorithm and run."""


@dataclass
class _Context:
    """What every worker process needs, built once per process."""

    seed: int
    scenario: Scenario
    environment: Environment
    pipeline: Pipeline
    algorithms: list[tuple[str, dict[str, Any]]]  # name, resolved options
    initial: InitialState
    late: LateSettings
    faults: RsuFaults | None


_CONTEXT: _Context | None = None


def initial_state(scenario: Scenario) -> InitialState:
    """The scenario's true initial position and velocity, 1 m and 1 m/s standard deviation."""
    xp, xv, _xa, yp, yv, _ya, _phi, _omega = scenario.initial_state
    return InitialState(x=xp, y=yp, vx=xv, vy=yv, position_std=1.0, velocity_std=1.0)


def _init_worker(
    specs: tuple[tuple[str, dict[str, Any]], ...], seed: int, late: LateSettings, faults: RsuFaults | None
) -> None:
    global _CONTEXT
    scenario = rsu_imu_paper_scenario()
    pipeline = get_pipeline(PIPELINE)
    algorithms = [(name, pipeline.resolve_options(options)) for name, options in specs]
    _CONTEXT = _Context(
        seed, scenario, environment(scenario), pipeline, algorithms, initial_state(scenario), late, faults
    )


def _run_chunk(chunk: range) -> Totals:
    """Totals over the runs of ``chunk``, summed in run order."""
    context = _CONTEXT
    assert context is not None, "worker not initialised"
    truth = context.scenario.truth
    true_x, true_y, true_vx, true_vy = truth.x[1:], truth.y[1:], truth.vx[1:], truth.vy[1:]
    totals: Totals | None = None
    for run in chunk:
        rng = np.random.default_rng([context.seed, run])
        observations = [obs for epoch in rsu_imu_epochs(context.scenario, rng) for obs in epoch]
        event = None
        if context.faults is not None:  # its own generator: the noise of every run is as without faults
            observations, event = inject(
                observations, context.faults, np.random.default_rng([context.seed, run, 2])
            )
        sums = {}
        for name, options in context.algorithms:
            state = context.pipeline.create(options, context.initial)
            started = time.perf_counter()
            try:
                fixes, _ = context.pipeline.process(state, observations, context.environment)
            except Exception as exc:  # noqa: BLE001 - any failure of a filter must name the algorithm and run, not kill the pool silently
                raise RunFailed(f"{name} failed in run {run} (seed {context.seed}): {exc}") from None
            elapsed = time.perf_counter() - started
            if len(fixes) != true_x.size or any(fix.x is None or fix.vx is None for fix in fixes):
                raise RunFailed(f"{name} run {run}: expected {true_x.size} tracking fixes, got {len(fixes)}")
            estimates = np.array([(fix.x, fix.y, fix.vx, fix.vy) for fix in fixes], dtype=float)
            pos_sq = (estimates[:, 0] - true_x) ** 2 + (estimates[:, 1] - true_y) ** 2
            vel_sq = (estimates[:, 2] - true_vx) ** 2 + (estimates[:, 3] - true_vy) ** 2
            models = options["models"]
            probabilities = None
            if len(models) > 1:
                probabilities = np.array(
                    [[fix.model_probabilities[model] for model in models] for fix in fixes], dtype=float
                )
            extra = late_columns(
                context.pipeline,
                options,
                context.initial,
                observations,
                context.environment,
                np.column_stack([true_x, true_y, true_vx, true_vy]),
                context.late,
                np.random.default_rng([context.seed, run, 1]),  # the same deliveries for every algorithm
            )
            integrity = tally(
                fixes,
                np.column_stack([true_x, true_y]),
                truth.t[1:],
                observations,
                options["alert_limit_m"],
                event,
            )
            sums[name] = Sums(pos_sq, vel_sq, probabilities, elapsed, len(fixes), extra, integrity)
        run_totals = Totals(1, sums)
        totals = run_totals if totals is None else combine(totals, run_totals)
    assert totals is not None
    return totals


def monte_carlo(
    algorithms: list[Algorithm],
    runs: int,
    seed: int,
    workers: int,
    progress: Progress | None = None,
    late: LateSettings | None = None,
    faults: RsuFaults | None = None,
) -> Totals:
    """Sums over ``runs`` runs, identical for any ``workers``; ``late``: the smoothing and late-delivery
    columns to add (``rsu_imu_late``); ``faults``: RSU faults to inject (``sim.faults``)."""
    specs = tuple((algorithm.name, algorithm.options) for algorithm in algorithms)
    return montecarlo.run_chunks(
        _run_chunk,
        combine,
        montecarlo.chunk_runs(runs),
        workers,
        _init_worker,
        (specs, seed, late or LateSettings(), faults),
        progress,
    )


@dataclass(frozen=True)
class Result:
    """One algorithm's RMSE curves (eqs. 39-40), their means and the time per step."""

    algorithm: Algorithm
    pos_rmse: np.ndarray  # (K,) m
    vel_rmse: np.ndarray  # (K,) m/s
    probabilities: np.ndarray | None  # (K, models) mean over runs
    step_us: float
    extra: dict[str, float] = field(default_factory=dict)  # mean RMSE of each rsu_imu_late column
    integrity: IntegrityTally = field(default_factory=IntegrityTally)

    @property
    def algorithm_alert_limit(self) -> float:
        """The alert limit (m) the algorithm's sessions ran with."""
        return float(get_pipeline(PIPELINE).resolve_options(self.algorithm.options)["alert_limit_m"])

    @property
    def pos_mean(self) -> float:
        return float(np.mean(self.pos_rmse))

    @property
    def vel_mean(self) -> float:
        return float(np.mean(self.vel_rmse))


def results(algorithms: list[Algorithm], totals: Totals) -> dict[str, Result]:
    """Per-algorithm RMSE curves and means from the Monte Carlo sums."""
    out = {}
    for algorithm in algorithms:
        sums = totals.sums[algorithm.name]
        probabilities = None if sums.probabilities is None else sums.probabilities / totals.runs
        out[algorithm.name] = Result(
            algorithm,
            np.sqrt(sums.pos_sq / totals.runs),
            np.sqrt(sums.vel_sq / totals.runs),
            probabilities,
            sums.seconds / sums.epochs * 1e6,
            {name: float(np.mean(np.sqrt(values / totals.runs))) for name, values in sums.extra.items()},
            sums.integrity,
        )
    return out
