"""Benchmark: gnss_tight's time per epoch and its filter step's, this checkout against another one ("before").

The real rover recording (tests/data/gnss-rover: GPS + BeiDou + Galileo with Doppler and carrier phase, about
20 pseudoranges per epoch), one-epoch batches straight into the pipeline (no HTTP), on the defaults with
``seed`` 1. Each (filter, code) run is a child process with its own PYTHONPATH, so two versions of the
package can be compared; the runs are interleaved repetition by repetition (before, now, before, now, ...)
so that load on the machine hits both alike. Prints, per filter and code, the median ms per epoch (whole
``process`` call) and of the filter's ``step`` alone over all repetitions, each repetition's epoch median,
and the load average before and after; wall-clock time and the CPU time of the thread
(``time.thread_time``), which waiting for a core on a loaded machine does not inflate (shared caches and
hyperthreads still slow it).

    git -C /work/main archive <commit> service | tar -x -C /tmp/upf-base     # the code to compare with
    python bench/gnss_upf_epoch.py --before /tmp/upf-base/service [--epochs 300] [--reps 3] \\
        [--filters upf,pf,ukf] [--particles 200]

Without ``--before`` only this checkout runs. ``--now-option NAME=JSON`` (repeatable) sets a session option
for this checkout's runs only, so ``--before`` of this same checkout's service/ compares an option with the
defaults, e.g. ``--before service --now-option 'carrier_smoothing="hatch+tdcp"'``; ``--before-option``
likewise for the "before" runs (the same option on both sides compares two versions of its code).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SERVICE = HERE.parent / "service"


def child(filter_name: str, particles: int, epochs: int, extra: dict[str, object]) -> None:
    """Run the recording through the pipeline in this process; print the per-epoch times as JSON."""
    sys.path.insert(0, str(HERE))
    from edgepos.core.particles import PARTICLE_FILTERS
    from edgepos.pipelines.gnss_tight import GnssTightPipeline
    from gnss_tight_options import load

    step_ms: list[float] = []
    step_cpu: list[float] = []
    cls = PARTICLE_FILTERS[filter_name]
    original = cls.step

    def timed(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        start, cpu = time.perf_counter(), time.thread_time()
        try:
            return original(self, *args, **kwargs)
        finally:
            step_ms.append(1000.0 * (time.perf_counter() - start))
            step_cpu.append(1000.0 * (time.thread_time() - cpu))

    cls.step = timed  # type: ignore[method-assign]
    observations, environment = load(epochs)
    pipeline = GnssTightPipeline()
    options = pipeline.resolve_options({"seed": 1, "filter": filter_name, "particles": particles, **extra})
    state = pipeline.create(options, None)
    epoch_ms, steps, epoch_cpu, steps_cpu = [], [], [], []
    for epoch in observations:
        before = len(step_ms)
        start, cpu = time.perf_counter(), time.thread_time()
        _, state = pipeline.process(state, epoch, environment)
        epoch_ms.append(1000.0 * (time.perf_counter() - start))
        epoch_cpu.append(1000.0 * (time.thread_time() - cpu))
        steps.append(sum(step_ms[before:]))
        steps_cpu.append(sum(step_cpu[before:]))
    print(json.dumps({"epoch": epoch_ms, "step": steps, "epoch_cpu": epoch_cpu, "step_cpu": steps_cpu}))


def run(
    service: Path, filter_name: str, particles: int, epochs: int, extra: dict[str, object]
) -> dict[str, list[float]]:
    env = dict(os.environ, PYTHONPATH=f"{service}{os.pathsep}{SERVICE.parent / 'client'}")
    command = [sys.executable, __file__, "--child", filter_name, "--particles", str(particles)]
    command += ["--child-options", json.dumps(extra)]
    out = subprocess.run(
        [*command, "--epochs", str(epochs)], env=env, check=True, capture_output=True, text=True
    )
    result: dict[str, list[float]] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, help="the service/ directory of the code to compare with")
    parser.add_argument("--epochs", type=int, default=300)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--filters", default="upf,pf,ukf")
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--now-option", action="append", default=[], metavar="NAME=JSON")
    parser.add_argument("--before-option", action="append", default=[], metavar="NAME=JSON")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--child-options", default="{}", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.particles, args.epochs, json.loads(args.child_options))
        return
    now_options = {k: json.loads(v) for k, v in (o.split("=", 1) for o in args.now_option)}
    before_options = {k: json.loads(v) for k, v in (o.split("=", 1) for o in args.before_option)}
    codes = {"now": SERVICE}
    if args.before is not None:
        codes = {"before": args.before.resolve(), **codes}
    filters = args.filters.split(",")
    load_before = os.getloadavg()
    results: dict[tuple[str, str], dict[str, list[float]]] = {}
    per_rep: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.reps):
        for filter_name in filters:
            for code, service in codes.items():
                extra = now_options if code == "now" else before_options
                times = run(service, filter_name, args.particles, args.epochs, extra)
                key = (filter_name, code)
                bucket = results.setdefault(key, {name: [] for name in times})
                for name, values in times.items():
                    bucket[name].extend(values)
                per_rep.setdefault(key, []).append(statistics.median(times["epoch"]))
    load_after = os.getloadavg()
    print(
        f"{args.epochs} epochs x {args.reps} repetitions, {args.particles} particles; load average "
        f"{load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f} before, "
        f"{load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f} after"
    )
    print(
        f"{'filter':6s} {'code':6s} {'epoch ms':>9s} {'step ms':>8s} {'epoch cpu':>9s} {'step cpu':>8s}"
        "  epoch median per repetition (wall)"
    )
    for (filter_name, code), times in results.items():
        reps = ", ".join(f"{m:.2f}" for m in per_rep[(filter_name, code)])
        print(
            f"{filter_name:6s} {code:6s} {statistics.median(times['epoch']):9.2f} "
            f"{statistics.median(times['step']):8.2f} {statistics.median(times['epoch_cpu']):9.2f} "
            f"{statistics.median(times['step_cpu']):8.2f}  {reps}"
        )


if __name__ == "__main__":
    main()
