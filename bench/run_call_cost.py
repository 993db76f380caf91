"""Benchmark: what one compiled call of a run of epochs costs apart from its epochs, the bound on what
stepping several sessions' batches in one call (issue 19's "cross-session batching") could save.

A 20-epoch batch of the ``rsu_imu`` pipeline (registry wrappers, the integrity monitor on or off,
timestamps jittered by up to +-2 ms) is processed once with ``kernels_run.run_epochs`` watched, to
capture the arguments of its run. Then, interleaved, thread CPU time of: the same call cut to no epoch
(the dispatcher's typing and unboxing of its arguments and the kernel's set-up: what a call costs
whatever it steps), the whole run, and the whole ``process`` of the batch. Merging N sessions' runs
into one call would save at most (N - 1) fixed costs; everything else in ``process`` is per session.

    python bench/run_call_cost.py [--repeats N]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from edgepos.core import kernels_run
from edgepos.core.compiled import warm_up
from edgepos.pipelines.base import InitialState
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs

BATCH_EPOCHS = 20


def cpu_us(action: Callable[..., Any], *arguments: Any) -> float:
    start = time.thread_time_ns()
    action(*arguments)
    return (time.thread_time_ns() - start) / 1e3


def measure(integrity: bool, repeats: int) -> dict[str, float]:
    scenario = rsu_imu_paper_scenario()
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(7))
    env = environment(scenario)
    pipeline = get_pipeline("rsu_imu")
    options = pipeline.resolve_options({"integrity": integrity})
    x0 = scenario.initial_state
    state = pipeline.create(options, InitialState(x0[0], x0[3], x0[1], x0[4]))
    warmup = 200
    for first in range(0, warmup, BATCH_EPOCHS):
        _, state = pipeline.process(state, [o for e in epochs[first : first + BATCH_EPOCHS] for o in e], env)
    shifts = np.random.default_rng(11).uniform(-0.002, 0.002, BATCH_EPOCHS).tolist()
    batch = [
        dataclasses.replace(o, t=o.t + shift)
        for shift, epoch in zip(shifts, epochs[warmup : warmup + BATCH_EPOCHS])
        for o in epoch
    ]
    captured: list[list[Any]] = []
    kernel: Any = kernels_run.run_epochs  # a numba dispatcher: its .py_func names the arguments

    def watched(*arguments: Any) -> int:
        captured.append([a.copy() if isinstance(a, np.ndarray) else a for a in arguments])
        return int(kernel(*arguments))

    vars(kernels_run)["run_epochs"] = watched  # the module attribute compiled_run calls through
    try:
        pipeline.process(state, batch, env)
    finally:
        vars(kernels_run)["run_epochs"] = kernel
    if len(captured) != 1:
        raise SystemExit(f"expected the batch to make one run, it made {len(captured)}")
    code = kernel.py_func.__code__
    arguments = dict(zip(code.co_varnames[: code.co_argcount], captured[0], strict=True))
    epochs_in_run = len(arguments["times"])

    def fresh(epochs_taken: int) -> list[Any]:
        """The run's arguments with their first ``epochs_taken`` epochs, writable arrays copied (the
        kernel writes the bank and its outputs in place)."""
        cut = dict(arguments, times=arguments["times"][:epochs_taken])
        return [v.copy() if isinstance(v, np.ndarray) and v.flags.writeable else v for v in cut.values()]

    timings: dict[str, list[float]] = {"call, no epoch": [], "call, whole run": [], "process": []}
    for _ in range(repeats):
        empty, whole = fresh(0), fresh(epochs_in_run)
        timings["call, no epoch"].append(cpu_us(kernel, *empty))
        timings["call, whole run"].append(cpu_us(kernel, *whole))
        timings["process"].append(cpu_us(pipeline.process, state, batch, env))
    result = {name: statistics.median(values) for name, values in timings.items()}
    result.update({f"{name} min": min(values) for name, values in timings.items()})
    result["epochs"] = epochs_in_run
    result["arguments"] = len(arguments)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2000)
    args = parser.parse_args()
    load_before = os.getloadavg()
    warm_up()
    print(f"load average before: {load_before[0]:.2f}")
    for integrity in (True, False):
        r = measure(integrity, args.repeats)
        fixed, run, process = r["call, no epoch"], r["call, whole run"], r["process"]
        print(
            f"\nintegrity monitor {'on' if integrity else 'off'}: a run of {r['epochs']:.0f} epochs, one call of {r['arguments']:.0f} arguments"
        )
        for name in ("call, no epoch", "call, whole run", "process"):
            print(f"  {name:16s} median {r[name]:8.1f} us   minimum {r[name + ' min']:8.1f} us")
        print(
            f"  the call's fixed cost: {fixed:.1f} us per batch, {fixed / r['epochs']:.2f} us per epoch,"
            f" {100 * fixed / run:.1f} % of the run, {100 * fixed / process:.1f} % of the batch's process"
        )
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
