"""Benchmark: CPU time of one batch through every registered pipeline, over a grid of options and batch
shapes, beside what the cost model (``edgepos.pipelines.cost``) predicts for it.

For each case a session state is brought to a realistic point (a converged track; for the particle filters
also right after initialisation, where the PF's progressive correction runs several stages) and the same
batch is run through ``pipeline.process`` from that same state several times (process is pure: same
state, same batch, same work). Each run is timed with ``time.thread_time()`` (CPU of this thread only:
other processes on the box do not count, though they still slow it through shared caches), after warm-up
calls so that no numba compilation or first-call cache is timed. edgepos is imported before numpy, so BLAS
runs on this thread alone, as in the service.

Workloads: rsu_imu on the paper scenario (timestamps jittered by a few ms, as real clocks are, so that no
interval's F and Q come from a cache), with a denser RSU layout for more RSUs per epoch; gnss_tight on the
real rover recording (tests/data/gnss-rover; 6, 15, 22 pseudoranges per epoch from GPS + BeiDou +
Galileo, 40 by repeating the strongest ones) with and without 10 Hz RISS samples built from the reference
trajectory; v2v_coop and v2x_federated on their simulators, with more neighbours made by shifted copies of
the simulated ones (tracks published with ``pipelines.tracks.publish``, kept long enough that every range
of the batch finds its neighbour).

Prints one row per case: pipeline, config, epochs, measurements per epoch (most of each kind), CPU ms per
batch (median; max), per epoch, the model's prediction and measured / predicted; then the load average.

    python bench/batch_cost.py [--only rsu_imu,gnss_tight] [--reps 3] [--quick] [--json FILE] [--fit]
    python bench/batch_cost.py --from-json run-1.json run-2.json run-3.json    # constants for CALIBRATION

``--fit`` (or ``--from-json`` over several runs, each case at the median of its runs) prints, per pipeline,
the constants of the tightest upper envelope of the measured medians over the cost model's features (a
linear programme; see ``edgepos.pipelines.cost``), to paste into ``CALIBRATION``. The full grid takes
about four minutes on the 2-core box under load; ``--quick`` about a quarter of that.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import platform
import statistics
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import edgepos  # noqa: F401  (first: pins BLAS to one thread before numpy loads)
import numpy as np
from edgepos.core.compiled import warm_up
from edgepos.core.observations import (
    GyroObservation,
    Observation,
    PseudorangeObservation,
    RissObservation,
    RsuRangeObservation,
    V2vRangeObservation,
)
from edgepos.pipelines import tracks
from edgepos.pipelines.base import InitialState, NeighbourTrack, Rsu, StaticEnvironment
from edgepos.pipelines.registry import PIPELINES, get_pipeline

ROOT = Path(__file__).resolve().parents[1]
GNSS_DATA = ROOT / "tests" / "data" / "gnss-rover"


@dataclass
class Case:
    """One timed batch: ``pipeline.process(state, batch, environment)`` with the session's raw options."""

    pipeline: str
    config: str
    options: dict[str, Any]
    state: bytes
    batch: list[Observation]
    environment: StaticEnvironment
    note: str = ""
    resolved: dict[str, Any] = field(default_factory=dict)


def epoch_shape(batch: Sequence[Observation]) -> tuple[int, dict[str, int]]:
    """Distinct epochs and, per kind, the most observations of it in one epoch."""
    per_epoch: dict[float, Counter] = {}
    for observation in batch:
        per_epoch.setdefault(observation.t, Counter())[observation.kind] += 1
    most: Counter = Counter()
    for counts in per_epoch.values():
        for kind, count in counts.items():
            most[kind] = max(most[kind], count)
    return len(per_epoch), dict(sorted(most.items()))


def time_case(case: Case, reps: int, warm: int = 1) -> list[float]:
    """CPU seconds of each of ``reps`` runs, after ``warm`` untimed ones."""
    if case.note == PF_WORST:
        with pf_stages_forced():
            return time_case(dataclasses.replace(case, note=""), reps, warm)
    pipeline = get_pipeline(case.pipeline)
    for _ in range(warm):
        pipeline.process(case.state, case.batch, case.environment)
    out = []
    for _ in range(reps):
        started = time.thread_time()
        pipeline.process(case.state, case.batch, case.environment)
        out.append(time.thread_time() - started)
    return out


@contextlib.contextmanager
def pf_stages_forced() -> Iterator[None]:
    """The PF's progressive correction at its most stages (8): each takes 1/8 of the likelihood, after
    the bisection that would have chosen the power (timed, result unused)."""
    from edgepos.core.particles import pf

    original = pf._largest_power

    def eighth(log_weights, log_likelihood, remaining, target):
        original(log_weights, log_likelihood, remaining, target)  # its bisection's cost, result unused
        return min(remaining, 0.125)

    pf._largest_power = eighth
    try:
        yield
    finally:
        pf._largest_power = original


def advance(pipeline_name: str, state: bytes, epochs: Sequence[Sequence[Observation]], environment) -> bytes:
    pipeline = get_pipeline(pipeline_name)
    for epoch in epochs:
        _, state = pipeline.process(state, list(epoch), environment)
    return state


def flatten(epochs: Sequence[Sequence[Observation]]) -> list[Observation]:
    return [o for epoch in epochs for o in epoch]


# -- rsu_imu -------------------------------------------------------------------------------------
RSU_MODEL_SETS: dict[str, tuple[list[str], list[str]]] = {
    # label: (models, priority); "cs" marks the current-statistical model, which the compiled kernels do not
    # cover: a bank with it runs on the numpy reference.
    "1:ca": (["ca"], []),
    "2:ca,at": (["ca", "at"], ["ca"]),
    "3:ca,at,singer": (["ca", "at", "singer"], ["ca", "at"]),
    "5:cv,ca,ct,at,singer": (["cv", "ca", "ct", "at", "singer"], ["ca", "at"]),
    "1:cs": (["current_statistical"], []),
    "3:ca,at,cs": (["ca", "at", "current_statistical"], ["ca", "at"]),
    "6:all(cs)": (["cv", "ca", "ct", "at", "singer", "current_statistical"], ["ca", "at"]),
}


def rsu_imu_cases(quick: bool) -> Iterator[Case]:
    from edgepos.sim.scenarios import ROAD_EDGES, RSU_SETBACK, rsu_imu_paper_scenario
    from edgepos.sim.sensors import environment, rsu_imu_epochs

    paper = rsu_imu_paper_scenario()
    # A dense layout for many RSUs per epoch: 64 units every 28 m on both sides, all within 1 km.
    dense_rsus = tuple(
        Rsu(f"D{k:02d}", -300.0 + 14.0 * k, ROAD_EDGES[k % 2] + (-RSU_SETBACK if k % 2 == 0 else RSU_SETBACK))
        for k in range(64)
    )
    dense = dataclasses.replace(paper, rsus=dense_rsus, comm_radius=2000.0, max_rsus=64)
    pipeline = get_pipeline("rsu_imu")
    x0 = paper.initial_state
    initial = InitialState(x0[0], x0[3], x0[1], x0[4])
    warmup = 40  # epochs (2 s) from the known initial state: a converged bank

    def jittered(scenario, seed: int, gyros: int = 1) -> list[list[Observation]]:
        rng = np.random.default_rng(seed)
        epochs = rsu_imu_epochs(scenario, rng)
        jitter = rng.uniform(-0.003, 0.003, len(epochs))
        out = []
        for epoch, j in zip(epochs, jitter):
            moved = [dataclasses.replace(o, t=o.t + float(j)) for o in epoch]
            extra = [o for o in moved if isinstance(o, GyroObservation)] * (gyros - 1)
            out.append(
                moved
                + [dataclasses.replace(o, yaw_rate=o.yaw_rate + 1e-3 * (k + 1)) for k, o in enumerate(extra)]
            )
        return out

    paper_epochs = jittered(paper, 7)
    dense_epochs = jittered(dense, 8)
    dense_gyro_epochs = jittered(dense, 9, gyros=4)
    paper_env, dense_env = environment(paper), environment(dense)

    def case(label, options, epochs, env, count, note=""):
        resolved = pipeline.resolve_options(options)
        state = pipeline.create(resolved, initial)
        state = advance("rsu_imu", state, [flatten(epochs[:warmup])], env)
        batch = flatten(epochs[warmup : warmup + count])
        return Case("rsu_imu", label, options, state, batch, env, note)

    filters = ("ekf", "ukf", "ckf", "srukf")  # srukf: not covered by the compiled kernels
    sets = list(RSU_MODEL_SETS) if not quick else ["1:ca", "3:ca,at,singer", "6:all(cs)"]
    # Per-epoch cost: every filter x model set x handling, 20-epoch batches, paper layout (<= 4 RSUs).
    for filter_name in filters:
        for label in sets:
            if filter_name == "srukf" and label not in ("1:ca", "3:ca,at,singer", "6:all(cs)"):
                continue
            models, priority = RSU_MODEL_SETS[label]
            for handling in ("joint", "average"):
                options = {
                    "filter": filter_name,
                    "models": models,
                    "priority": priority,
                    "rsu_handling": handling,
                }
                yield case(
                    f"{filter_name} {label} {handling} max_rsus=4", options, paper_epochs, paper_env, 20
                )
    # RSUs per epoch: dense layout (64 heard), max_rsus 8..64, joint and average; 4 gyros per epoch.
    for filter_name in filters:
        for label in ("1:ca", "3:ca,at,singer", "6:all(cs)"):
            models, priority = RSU_MODEL_SETS[label]
            for handling in ("joint", "average"):
                sweep = (8, 16, 32, 64) if filter_name == "ckf" else (16, 64)
                for max_rsus in sweep:
                    options = {
                        "filter": filter_name,
                        "models": models,
                        "priority": priority,
                        "rsu_handling": handling,
                        "max_rsus": max_rsus,
                        "comm_radius": 2000.0,
                    }
                    count = 5 if max_rsus >= 32 else 10
                    yield case(
                        f"{filter_name} {label} {handling} max_rsus={max_rsus}",
                        options,
                        dense_epochs,
                        dense_env,
                        count,
                    )
                    if max_rsus == 64 and filter_name in ("ckf", "srukf"):
                        yield case(
                            f"{filter_name} {label} {handling} max_rsus=64 4gyro",
                            options,
                            dense_gyro_epochs,
                            dense_env,
                            count,
                        )
            if quick:
                break
    # The integrity monitor (options.integrity): the paper's 2IMM-CKF with its bank of sub-filters, on the
    # paper layout and with 8, 16 and 32 RSUs per epoch (one sub-filter per RSU used).
    for max_rsus in (4, 8, 16, 32):
        options = {"integrity": True, "max_rsus": max_rsus, "comm_radius": 2000.0}
        scenario_epochs, scenario_env = (
            (paper_epochs, paper_env) if max_rsus == 4 else (dense_epochs, dense_env)
        )
        for integrity in (False, True):
            yield case(
                f"ckf 3:ca,at,singer joint max_rsus={max_rsus}{' integrity' if integrity else ''}",
                {**options, "integrity": integrity},
                scenario_epochs,
                scenario_env,
                20 if max_rsus == 4 else 10,
            )
        if quick:
            break
    # Epochs per batch: the fixed cost of a batch and linearity in epochs.
    for label in ("3:ca,at,singer", "6:all(cs)"):
        models, priority = RSU_MODEL_SETS[label]
        for count in (1, 5, 20, 100):
            options = {"filter": "ckf", "models": models, "priority": priority}
            yield case(f"ckf {label} joint max_rsus=4", options, paper_epochs, paper_env, count)
    # Gyro-only epochs (the most epochs a batch of N measurements can have), and a fresh session.
    options = {"filter": "ckf", "models": RSU_MODEL_SETS["6:all(cs)"][0], "priority": ["ca", "at"]}
    gyro_only = [[o for o in epoch if isinstance(o, GyroObservation)] for epoch in paper_epochs]
    resolved = pipeline.resolve_options(options)
    state = advance(
        "rsu_imu", pipeline.create(resolved, initial), [flatten(paper_epochs[:warmup])], paper_env
    )
    yield Case(
        "rsu_imu",
        "ckf 6:all(cs) gyro-only epochs",
        options,
        state,
        flatten(gyro_only[warmup : warmup + 100]),
        paper_env,
    )
    yield Case(
        "rsu_imu",
        "ckf 6:all(cs) fresh session (initialises)",
        options,
        pipeline.create(resolved, None),
        flatten(paper_epochs[:20]),
        paper_env,
    )


# -- gnss_tight ----------------------------------------------------------------------------------
def gnss_inputs(
    epochs: int, doppler: bool = False
) -> tuple[list[list[PseudorangeObservation]], StaticEnvironment, list[float]]:
    from edgepos.gnss.ephemerides import Ephemerides
    from edgepos.gnss.rinex_nav import read_navigation
    from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
    from edgepos.pipelines.gnss_recording import epoch_pseudoranges

    codes = {s: DEFAULT_CODES[s] for s in "GCE"}
    navigation = Ephemerides.from_navigation(read_navigation(str(GNSS_DATA / "broadcast-nav.rnx")))
    out, gpst = [], []
    for number, epoch in enumerate(read_epochs(str(GNSS_DATA / "rover-0-5min.rnx"), codes)):
        if number >= epochs:
            break
        out.append(epoch_pseudoranges(epoch, doppler=doppler, carrier=False))  # code (and Doppler) only
        gpst.append(float(epoch.gpst))
    return out, StaticEnvironment(navigation=navigation), gpst


def riss_samples(gpst: Sequence[float], rate_hz: float = 10.0) -> list[list[RissObservation]]:
    """RISS samples at ``rate_hz`` from each GNSS epoch to the next, from the reference trajectory: wheel
    speed = horizontal speed, yaw rate = rate of the velocity's direction (counter-clockwise), forward
    specific force = the speed's rate, lateral = speed x yaw rate (level road)."""
    from edgepos.gnss.geodesy import ecef_to_geodetic, enu_rotation
    from edgepos.gnss.spp import read_reference

    ref_t, ref_ecef = read_reference(str(GNSS_DATA / "reference-0-5min.csv"))
    lat, lon, _ = ecef_to_geodetic(ref_ecef[0])
    enu = (enu_rotation(float(lat), float(lon)) @ (ref_ecef - ref_ecef[0]).T).T
    step = 1.0 / rate_hz
    out = []
    for t in gpst:
        samples = []
        for k in range(round(rate_hz)):
            tk = t + k * step
            east = np.interp([tk - 0.5, tk + 0.5], ref_t, enu[:, 0])
            north = np.interp([tk - 0.5, tk + 0.5], ref_t, enu[:, 1])
            ve, vn = east[1] - east[0], north[1] - north[0]
            speed = math.hypot(ve, vn)
            e2 = np.interp([tk - 1.0, tk, tk + 1.0], ref_t, enu[:, 0])
            n2 = np.interp([tk - 1.0, tk, tk + 1.0], ref_t, enu[:, 1])
            h0, h1 = math.atan2(n2[1] - n2[0], e2[1] - e2[0]), math.atan2(n2[2] - n2[1], e2[2] - e2[1])
            yaw_rate = math.remainder(h1 - h0, 2 * math.pi) if speed > 1.0 else 0.0
            accel = math.hypot(e2[2] - e2[1], n2[2] - n2[1]) - math.hypot(e2[1] - e2[0], n2[1] - n2[0])
            samples.append(RissObservation(tk % 604800.0, speed, accel, speed * yaw_rate, yaw_rate))
        out.append(samples)
    return out


def pseudorange_subset(epoch: Sequence[PseudorangeObservation], count: int) -> list[PseudorangeObservation]:
    """``count`` pseudoranges of the epoch: the strongest, taken in turn from each constellation; more than
    the epoch has by repeating the strongest (offset by centimetres), as a client may send."""
    by_system: dict[str, list[PseudorangeObservation]] = {}
    for o in sorted(epoch, key=lambda o: -o.cn0):
        by_system.setdefault(o.system, []).append(o)
    order = []
    while any(by_system.values()):
        for system in sorted(by_system):
            if by_system[system]:
                order.append(by_system[system].pop(0))
    chosen = order[:count]
    k = 0
    while len(chosen) < count:
        o = order[k % len(order)]
        chosen.append(dataclasses.replace(o, pseudorange=o.pseudorange + 0.05 * (k + 1)))
        k += 1
    return chosen


GNSS_PARTICLES = (
    50,
    200,
    next(s.maximum for s in get_pipeline("gnss_tight").option_specs() if s.name == "particles"),
)
"""Particle counts timed: a few, the default and the most a session may ask for."""
PF_WORST = "pf: 8 likelihood stages forced"
"""Note of the cases timed with the PF's progressive correction forced to its most stages (the cost model's
assumption for the PF)."""
GNSS_PSEUDORANGES = (6, 15, 22, 40)


def gnss_cases(quick: bool) -> Iterator[Case]:
    epochs, env, gpst = gnss_inputs(40)
    with_doppler, _, _ = gnss_inputs(40, doppler=True)  # each Doppler one more row of the update
    riss = riss_samples(gpst)
    pipeline = get_pipeline("gnss_tight")
    warmup = 12
    configs: list[tuple[str, int]] = [("ukf", 1)]
    particles = GNSS_PARTICLES if not quick else GNSS_PARTICLES[1:]
    configs += [(f, n) for f in ("pf", "upf") for n in particles]
    for filter_name, count in configs:
        options = {"filter": filter_name, "seed": 1}
        if filter_name != "ukf":
            options["particles"] = count
        label = filter_name if filter_name == "ukf" else f"{filter_name} {count}"
        resolved = pipeline.resolve_options(options)
        fresh = pipeline.create(resolved, None)
        after_init = advance("gnss_tight", fresh, epochs[:1], env)
        converged = advance("gnss_tight", after_init, epochs[1:warmup], env)
        sizes = (1, 3) if count > 200 else (1, 5, 20)
        for prs in GNSS_PSEUDORANGES:
            for size in sizes:
                batch = flatten(pseudorange_subset(e, prs) for e in epochs[warmup : warmup + size])
                yield Case("gnss_tight", f"{label} {prs}pr", options, converged, batch, env)
                batch = flatten(pseudorange_subset(e, prs) for e in with_doppler[warmup : warmup + size])
                yield Case("gnss_tight", f"{label} {prs}pr+doppler", options, converged, batch, env)
        if filter_name == "pf":
            for prs in (6, 22, 40):
                batch = flatten(pseudorange_subset(e, prs) for e in epochs[warmup : warmup + 3])
                yield Case(
                    "gnss_tight", f"{label} {prs}pr 8 stages forced", options, converged, batch, env, PF_WORST
                )
        # Pseudoranges with large errors: the snapshot test excludes up to max_exclusions, the residual
        # test loses the track, the least squares start again.
        if count <= 1000:
            for exclusions in (4, 30):
                bad_options = {**options, "max_exclusions": exclusions}
                bad_state = advance(
                    "gnss_tight",
                    pipeline.create(pipeline.resolve_options(bad_options), None),
                    epochs[:warmup],
                    env,
                )
                noise = np.random.default_rng(11)
                batch = [
                    dataclasses.replace(o, pseudorange=o.pseudorange + float(noise.normal(0.0, 300.0)))
                    for e in epochs[warmup : warmup + 3]
                    for o in pseudorange_subset(e, 40)
                ]
                yield Case(
                    "gnss_tight",
                    f"{label} 40pr biased max_exclusions={exclusions}",
                    bad_options,
                    bad_state,
                    batch,
                    env,
                )
        # Right after initialisation (the PF's progressive correction takes several stages), and a fresh
        # session's first batch (least-squares initialisation).
        yield Case(
            "gnss_tight",
            f"{label} 22pr after init",
            options,
            after_init,
            flatten(epochs[1:4]),
            env,
            "after init",
        )
        yield Case("gnss_tight", f"{label} 22pr fresh", options, fresh, flatten(epochs[:3]), env, "fresh")
        # With RISS at 10 Hz: nine RISS-only epochs between GNSS epochs; the RISS model once the heading is known.
        with_riss = [list(e) + riss[k][:1] for k, e in enumerate(epochs)]
        riss_only = [[s] for k in range(len(epochs)) for s in riss[k][1:]]
        merged = sorted(flatten(with_riss) + flatten(riss_only), key=lambda o: o.t)
        grouped: list[list[Observation]] = []
        for o in merged:
            if grouped and grouped[-1][0].t == o.t:
                grouped[-1].append(o)
            else:
                grouped.append([o])
        index = {round(g[0].t, 3): n for n, g in enumerate(grouped)}
        start = index[round(epochs[warmup][0].t, 3)]
        riss_state = advance("gnss_tight", fresh, grouped[:start], env)
        sizes = (10, 30)
        for size in sizes:
            yield Case(
                "gnss_tight",
                f"{label} 22pr+riss 10Hz",
                options,
                riss_state,
                flatten(grouped[start : start + size]),
                env,
                "riss",
            )


# -- v2v_coop ------------------------------------------------------------------------------------
def shifted_track(track: NeighbourTrack, vehicle_id: str, dx: float, dy: float) -> NeighbourTrack:
    return NeighbourTrack(
        vehicle_id,
        tuple(dataclasses.replace(p, x=p.x + dx, y=p.y + dy) for p in track.points),
    )


V2V_SHIFTS = [(0.0, 0.0)] + [(12.0 * ((k % 6) - 2.5), 4.0 * (k // 6 + 1)) for k in range(40)]


def v2v_cases(quick: bool) -> Iterator[Case]:
    from edgepos.pipelines.v2v_coop import METHODS
    from edgepos.sim.v2v import VEHICLE_IDS, make_run

    run = make_run(1, 0, "straight")
    pipeline = get_pipeline("v2v_coop")
    warmup = 30
    ego = 0
    others = [j for j in range(len(VEHICLE_IDS)) if j != ego]
    rng = np.random.default_rng(5)

    def environment_and_epochs(
        method: str, ranges: int, end: int
    ) -> tuple[StaticEnvironment, list[list[Observation]]]:
        """Every vehicle's session run to ``end`` with the method, tracks kept whole; the ego's epochs with
        ``ranges`` ranges per epoch to the simulated neighbours and shifted copies of them."""
        options = pipeline.resolve_options({"method": method})
        states = {vid: pipeline.create(options, None) for vid in VEHICLE_IDS}
        published: dict[str, NeighbourTrack] = {}
        for k in range(end):
            snapshot = dict(published)
            for i, vid in enumerate(VEHICLE_IDS):
                fixes, states[vid] = pipeline.process(
                    states[vid], run.observations[i][k], StaticEnvironment(tracks=snapshot, vehicle_id=vid)
                )
                track = tracks.publish(vid, published.get(vid), fixes, keep=10_000)
                if track is not None:
                    published[vid] = track
        peers = []
        for shift_index, (dx, dy) in enumerate(V2V_SHIFTS):
            for j in others:
                peers.append(
                    (j, dx, dy, VEHICLE_IDS[j] if shift_index == 0 else f"{VEHICLE_IDS[j]}~{shift_index}")
                )
        peers = peers[:ranges]
        env_tracks = {}
        for j, dx, dy, pid in peers:
            env_tracks[pid] = shifted_track(published[VEHICLE_IDS[j]], pid, dx, dy)
        epochs = []
        for k in range(end):
            base = [o for o in run.observations[ego][k] if not isinstance(o, V2vRangeObservation)]
            t = float(run.times[k])
            for j, dx, dy, pid in peers:
                distance = float(np.linalg.norm(run.positions[j, k] + [dx, dy] - run.positions[ego, k]))
                base.append(
                    V2vRangeObservation(t, pid, range=max(distance + 2.0 * float(rng.standard_normal()), 0.0))
                )
            epochs.append(base)
        return StaticEnvironment(tracks=env_tracks, vehicle_id=VEHICLE_IDS[ego]), epochs

    for method in METHODS:
        range_counts = (3,) if method in ("gps", "gps_dr") else ((3, 8, 16, 32) if not quick else (3, 16))
        for ranges in range_counts:
            env, epochs = environment_and_epochs(method, ranges, 100)
            options = {"method": method}
            state = advance(
                "v2v_coop",
                pipeline.create(pipeline.resolve_options(options), None),
                [flatten(epochs[:1])],
                env,
            )
            for k in range(1, warmup):
                state = advance("v2v_coop", state, [epochs[k]], env)
            sizes = (1, 5, 20, 50) if ranges in (3, 16) else (5,)
            for size in sizes:
                yield Case(
                    "v2v_coop",
                    f"{method} {ranges} ranges",
                    options,
                    state,
                    flatten(epochs[warmup : warmup + size]),
                    env,
                )
            if ranges == 3:
                yield Case(
                    "v2v_coop",
                    f"{method} {ranges} ranges fresh",
                    options,
                    pipeline.create(pipeline.resolve_options(options), None),
                    flatten(epochs[:20]),
                    env,
                    "fresh",
                )


# -- v2x_federated -------------------------------------------------------------------------------
FEDERATED_KINDS = {
    "GPS": {"gnss_fix"},
    "GPS/DR": {"gnss_fix", "gyro", "odometer"},
    "GPS/DR/V2X": {"gnss_fix", "gyro", "odometer", "v2v_range", "rsu_range"},
}


def federated_cases(quick: bool) -> Iterator[Case]:
    from edgepos.sim.federated import make_run

    run = make_run(1, 0, "clean")
    pipeline = get_pipeline("v2x_federated")
    rng = np.random.default_rng(6)
    # The assisting vehicles' own sessions, tracks kept whole.
    assist_options = pipeline.resolve_options(None)
    states = {vid: pipeline.create(assist_options, None) for vid in run.neighbour_ids}
    published: dict[str, NeighbourTrack] = {}
    for step_fixes in run.neighbour_fixes:
        for vid in run.neighbour_ids:
            fixes, states[vid] = pipeline.process(
                states[vid], [step_fixes[vid]], StaticEnvironment(vehicle_id=vid)
            )
            track = tracks.publish(vid, published.get(vid), fixes, keep=10_000)
            if track is not None:
                published[vid] = track
    rsus = {f"R{k:02d}": Rsu(f"R{k:02d}", 15.0 * k - 100.0, 12.0 if k % 2 else -12.0) for k in range(64)}
    warmup = 30

    def epochs_with(v2v: int, rsu: int) -> tuple[StaticEnvironment, list[list[Observation]]]:
        peers = []
        for shift_index, (dx, dy) in enumerate(V2V_SHIFTS):
            for n, vid in enumerate(run.neighbour_ids):
                peers.append((n, dx, dy, vid if shift_index == 0 else f"{vid}~{shift_index}"))
        peers = peers[:v2v]
        env_tracks = {
            pid: shifted_track(published[run.neighbour_ids[n]], pid, dx, dy) for n, dx, dy, pid in peers
        }
        epochs = []
        for k, t in enumerate(run.times):
            x, y = run.truth[k, 0], run.truth[k, 3]
            base = [o for o in run.observations[k] if not isinstance(o, V2vRangeObservation)]
            for n, dx, dy, pid in peers:
                distance = float(np.hypot(*(run.neighbour_truth[k, n] + [dx, dy] - [x, y])))
                base.append(
                    V2vRangeObservation(
                        float(t), pid, range=max(distance + 3.0 * float(rng.standard_normal()), 0.0)
                    )
                )
            nearest = sorted(rsus.values(), key=lambda r: math.hypot(r.x - x, r.y - y))[:rsu]
            for r in nearest:
                base.append(
                    RsuRangeObservation(
                        float(t), r.id, math.hypot(r.x - x, r.y - y) + 3.0 * float(rng.standard_normal())
                    )
                )
            epochs.append(base)
        return StaticEnvironment(rsus=rsus, tracks=env_tracks, vehicle_id="target"), epochs

    shapes = [("GPS", 0, 0), ("GPS/DR", 0, 0)]
    shapes += [
        ("GPS/DR/V2X", v, r) for v, r in ((4, 0), (8, 0), (16, 0), (32, 0), (0, 16), (16, 16), (32, 32))
    ]
    if quick:
        shapes = [("GPS", 0, 0), ("GPS/DR/V2X", 4, 0), ("GPS/DR/V2X", 16, 16)]
    for method, v2v, rsu in shapes:
        env, epochs = epochs_with(v2v, rsu)
        kinds = FEDERATED_KINDS[method]
        epochs = [[o for o in e if o.kind in kinds] for e in epochs]
        for feedback in (True, False):
            options = {"feedback": feedback}
            state = pipeline.create(pipeline.resolve_options(options), None)
            state = advance("v2x_federated", state, epochs[:warmup], env)
            label = f"{method}{'' if feedback else ' nofeedback'} {v2v}v2v+{rsu}rsu"
            sizes = (1, 5, 20, 100) if feedback and (v2v, rsu) in ((0, 0), (4, 0), (16, 16)) else (5,)
            for size in sizes:
                yield Case(
                    "v2x_federated", label, options, state, flatten(epochs[warmup : warmup + size]), env
                )


GENERATORS: dict[str, Callable[[bool], Iterator[Case]]] = {
    "rsu_imu": rsu_imu_cases,
    "gnss_tight": gnss_cases,
    "v2v_coop": v2v_cases,
    "v2x_federated": federated_cases,
}


def predicted_s(case: Case) -> float | None:
    try:
        from edgepos.pipelines.cost import batch_cost_s
    except ImportError:
        return None
    return batch_cost_s(case.pipeline, case.resolved, case.batch)


def fit(rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per pipeline, the constants of the tightest upper envelope of the measured medians: a linear
    programme, minimise the sum of predicted / measured with every row predicted >= measured and every
    constant >= 0. Features no row exercises are reported (they would fit to 0)."""
    from edgepos.pipelines import cost
    from scipy.optimize import linprog

    out: dict[str, dict[str, float]] = {}
    for name in dict.fromkeys(row["pipeline"] for row in rows):
        model = cost.cost_model(name)
        features = list(model.features)
        matrix, measured = [], []
        for row in (r for r in rows if r["pipeline"] == name):
            options = get_pipeline(name).resolve_options(row["options"])
            summed = cost.batch_features(name, options, row["counts"])
            matrix.append([summed.get(f, 0.0) for f in features])
            measured.append(row["median_s"])
        a = np.array(matrix)
        y = np.array(measured)
        unused = [f for f, column in zip(features, a.T) if not column.any()]
        if unused:
            print(f"{name}: no measured row exercises {unused}; they fit to 0", file=sys.stderr)
        objective = (a / y[:, None]).sum(axis=0)
        result = linprog(objective, A_ub=-a, b_ub=-y, bounds=[(0, None)] * len(features), method="highs")
        if not result.success:
            raise RuntimeError(f"{name}: envelope fit failed: {result.message}")
        out[name] = {f: float(f"{value:.3g}") for f, value in zip(features, result.x)}
        ratios = (a @ result.x) / y
        print(
            f"{name}: envelope / measured over {len(y)} rows: min {ratios.min():.2f} median "
            f"{np.median(ratios):.2f} max {ratios.max():.2f}"
        )
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=",".join(GENERATORS), help="pipelines, comma-separated")
    parser.add_argument("--reps", type=int, default=3, help="timed runs per case (median reported)")
    parser.add_argument("--quick", action="store_true", help="a smaller grid")
    parser.add_argument("--json", type=Path, help="write every row here")
    parser.add_argument("--fit", action="store_true", help="print the envelope's constants for CALIBRATION")
    parser.add_argument(
        "--from-json",
        type=Path,
        nargs="+",
        help="fit earlier --json runs (each case at the median of its runs)",
    )
    args = parser.parse_args()
    if args.from_json:
        # Several runs: each case at the median of its runs' medians (one run's burst of contention from
        # other processes on the box moves single cases by up to 2x; MARGIN covers the spread).
        merged: dict[tuple, list[dict[str, Any]]] = {}
        for path in args.from_json:
            for row in json.loads(path.read_text())["rows"]:
                merged.setdefault((row["pipeline"], row["config"], row["epochs"]), []).append(row)
        rows = [
            {**runs[0], "median_s": statistics.median(r["median_s"] for r in runs)}
            for runs in merged.values()
        ]
        print(json.dumps(fit(rows), indent=4))
        return 0
    missing = set(PIPELINES) - set(GENERATORS)
    if missing:
        print(f"no workload for pipelines {sorted(missing)}", file=sys.stderr)
        return 2
    load_before = os.getloadavg()
    started = time.perf_counter()
    warm_up()
    print(
        f"python {platform.python_version()} on {platform.machine()}, {os.cpu_count()} cpus, "
        f"EDGEPOS_NUMBA={os.environ.get('EDGEPOS_NUMBA', '1')}; load average before {load_before[0]:.2f} "
        f"{load_before[1]:.2f} {load_before[2]:.2f}"
    )
    header = (
        f"{'pipeline':<13} {'config':<46} {'ep':>4} {'per epoch (most)':<34} {'ms/batch':>9} {'max':>8} "
        f"{'ms/epoch':>9} {'pred ms':>9} {'meas/pred':>9}"
    )
    print(header)
    rows = []
    loads = []
    for name in args.only.split(","):
        pipeline_started = time.perf_counter()
        for case in GENERATORS[name](args.quick):
            case.resolved = get_pipeline(case.pipeline).resolve_options(case.options)
            times = time_case(case, args.reps)
            loads.append(os.getloadavg()[0])
            epochs, most = epoch_shape(case.batch)
            median = statistics.median(times)
            predicted = predicted_s(case)
            shape = " ".join(f"{k}={v}" for k, v in most.items())
            ratio = "" if not predicted else f"{median / predicted:9.2f}"
            pred = "" if not predicted else f"{1e3 * predicted:9.2f}"
            print(
                f"{case.pipeline:<13} {case.config:<46} {epochs:>4} {shape:<34} {1e3 * median:>9.2f} "
                f"{1e3 * max(times):>8.2f} {1e3 * median / epochs:>9.3f} {pred} {ratio}",
                flush=True,
            )
            rows.append(
                {
                    "pipeline": case.pipeline,
                    "config": case.config,
                    "note": case.note,
                    "options": case.options,
                    "epochs": epochs,
                    "per_epoch_most": most,
                    "observations": len(case.batch),
                    "counts": [dict(c) for c in _epoch_counts(case.batch)],
                    "cpu_s": times,
                    "median_s": median,
                    "predicted_s": predicted,
                }
            )
        print(f"# {name}: {time.perf_counter() - pipeline_started:.0f} s wall", flush=True)
    load_after = os.getloadavg()
    print(
        f"load average after {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f}; 1-minute load "
        f"during the run: median {statistics.median(loads):.2f}, max {max(loads):.2f}; "
        f"{time.perf_counter() - started:.0f} s wall"
    )
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "python": platform.python_version(),
                    "machine": platform.machine(),
                    "cpus": os.cpu_count(),
                    "load_before": load_before,
                    "load_after": load_after,
                    "load_during": loads,
                    "rows": rows,
                },
                indent=1,
            )
        )
    if args.fit:
        print(json.dumps(fit(rows), indent=4))
    return 0


def _epoch_counts(batch: Sequence[Observation]) -> list[Counter]:
    """Per epoch (by time), the observations of each kind and the Dopplers they carry, as the cost model
    counts them (``cost.epoch_counts``)."""
    from edgepos.pipelines import cost

    by_time = {observation.t: None for observation in batch}
    counts = cost.epoch_counts(batch)
    ordered = dict(zip(by_time, counts, strict=True))
    return [Counter(ordered[t]) for t in sorted(ordered)]


if __name__ == "__main__":
    raise SystemExit(main())
