"""Same-process A/B of the rsu_imu integrity monitor: another tree's ``core/integrity.py``,
``core/integrity_bank.py``, ``core/kernels_integrity.py`` and ``pipelines/integrity.py`` (loaded under
other module names) against this tree's, interleaved with the pipeline without the monitor.

The pipeline per epoch of a 20-epoch batch with timestamps jittered by up to +-2 ms, as
``bench/filter_step.py`` times it: without the monitor, with the other tree's, with this tree's, one
batch of each back to back, in rotating order. Prints per variant the median and minimum per epoch,
the monitor's share by medians, by the median of back-to-back triples and by thread CPU (medians).
Both monitored sessions must give the same fixes and states, batch by batch. On a shared machine two
trees timed in one process compare where two processes timed apart do not.

    PYTHONPATH=<this tree>/service python bench/monitor_ab.py --base <other tree> [--batches N]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib.util
import os
import pickle
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np
from edgepos.core.compiled import warm_up
from edgepos.pipelines import rsu_imu
from edgepos.pipelines.base import InitialState
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs

# the monitor's modules, in import order, and the names the other tree's copies get
MODULES = (
    ("core/integrity.py", "edgepos.core.integrity"),
    ("core/integrity_bank.py", "edgepos.core.integrity_bank"),
    ("core/kernels_integrity.py", "edgepos.core.kernels_integrity"),
    ("pipelines/integrity.py", "edgepos.pipelines.integrity"),
)
_RENAMED = re.compile(
    r"edgepos\.(core\.integrity_bank|core\.kernels_integrity|core\.integrity|pipelines\.integrity)\b"
)
_FROM_CORE = re.compile(r"from edgepos\.core import (integrity_bank|kernels_integrity|integrity)\b")


def load_base(tree: Path) -> ModuleType:
    """The other tree's ``pipelines/integrity`` with its own copies of the monitor's core modules (their
    imports of each other renamed); copied to a directory named by their content, so that numba's
    on-disk cache serves the next run."""
    package = tree / "service" / "edgepos"
    sources = {name: (package / path).read_text() for path, name in MODULES}
    digest = hashlib.sha256("".join(sources.values()).encode()).hexdigest()[:16]
    directory = Path(tempfile.gettempdir()) / f"edgepos-monitor-ab-{digest}"
    directory.mkdir(exist_ok=True)
    module = None
    for _, name in MODULES:
        renamed = name + "_ab_base"
        path = directory / (renamed.rsplit(".", 1)[1] + ".py")
        text = _RENAMED.sub(lambda match: f"edgepos.{match.group(1)}_ab_base", sources[name])
        text = _FROM_CORE.sub(r"from edgepos.core import \1_ab_base as \1", text)
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
        spec = importlib.util.spec_from_file_location(renamed, path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[renamed] = module
        spec.loader.exec_module(module)
    assert module is not None
    return module


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--base", type=Path, required=True, help="the other tree (a checkout of the repository)"
    )
    parser.add_argument("--batches", type=int, default=300, help="20-epoch batches per variant")
    args = parser.parse_args()
    load_before = os.getloadavg()
    warm_up()
    base = load_base(args.base)
    this_monitor = (rsu_imu.monitored_update, rsu_imu.bank_from_tail)
    base_monitor = (base.monitored_update, base.bank_from_tail)

    scenario = rsu_imu_paper_scenario()
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(7))
    env = environment(scenario)
    pipeline = get_pipeline("rsu_imu")
    x0 = scenario.initial_state
    initial = InitialState(x0[0], x0[3], x0[1], x0[4])

    def use(monitor: tuple) -> None:
        rsu_imu.monitored_update, rsu_imu.bank_from_tail = monitor

    def converged(integrity: bool, monitor: tuple) -> bytes:  # 200 epochs in 20-epoch batches, as filter_step
        use(monitor)
        state = pipeline.create(pipeline.resolve_options({"integrity": integrity}), initial)
        for first in range(0, 200, 20):
            _, state = pipeline.process(
                state, [o for epoch in epochs[first : first + 20] for o in epoch], env
            )
        return state

    rng = np.random.default_rng(11)
    later = epochs[200:220]
    batches = []
    for _ in range(args.batches):
        shifts = rng.uniform(-0.002, 0.002, len(later)).tolist()
        batches.append([dataclasses.replace(o, t=o.t + s) for s, epoch in zip(shifts, later) for o in epoch])
    cases = {
        "no monitor": (converged(False, this_monitor), this_monitor),
        "base": (converged(True, base_monitor), base_monitor),
        "this tree": (converged(True, this_monitor), this_monitor),
    }
    # the same answers: fixes and states, batch by batch, on a few batches
    for batch in batches[:20]:
        answers = []
        for name in ("base", "this tree"):
            use(cases[name][1])
            fixes, state = pipeline.process(cases[name][0], batch, env)
            answers.append((pickle.dumps(fixes, protocol=5), state))
        if answers[0] != answers[1]:
            print("the two trees' monitors give different fixes or states")
            return 1
    wall: dict[str, list[float]] = {name: [] for name in cases}
    cpu: dict[str, list[float]] = {name: [] for name in cases}
    order = list(cases)
    for index, batch in enumerate(batches * 3):
        for name in order[index % 3 :] + order[: index % 3]:  # each first, second and third alike
            state, monitor = cases[name]
            use(monitor)
            start, start_cpu = time.perf_counter(), time.thread_time()
            pipeline.process(state, batch, env)
            wall[name].append((time.perf_counter() - start) * 1e6 / len(later))
            cpu[name].append((time.thread_time() - start_cpu) * 1e6 / len(later))
    use(this_monitor)
    print(
        f"load average before: {load_before[0]:.2f}, after: {os.getloadavg()[0]:.2f}; "
        f"{3 * args.batches} batches of {len(later)} jittered epochs per variant, interleaved"
    )
    off = statistics.median(wall["no monitor"])
    off_cpu = statistics.median(cpu["no monitor"])
    for name in cases:
        line = f"{name:12s} median {statistics.median(wall[name]):7.1f} us  min {min(wall[name]):7.1f} us"
        if name != "no monitor":
            triples = statistics.median(
                w / o - 1.0 for w, o in zip(wall[name], wall["no monitor"], strict=True)
            )
            line += (
                f"  monitor +{100 * (statistics.median(wall[name]) / off - 1):.1f} % (medians), "
                f"+{100 * triples:.1f} % (triples), +{100 * (statistics.median(cpu[name]) / off_cpu - 1):.1f} % "
                f"(thread CPU), +{100 * (min(wall[name]) / min(wall['no monitor']) - 1):.1f} % (minimums)"
            )
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
