"""Benchmark: the same checkout on two Python interpreters (venvs), interleaved, in thread CPU time.

Why: the service's worker spends most of its CPU in the interpreter (perf on a loaded worker: about two
thirds in libpython), so how CPython itself was built matters as much as a round of code changes. Each
interpreter runs, in a child process of its own, alternating round by round:

* a pure-Python loop (dicts, lists, small objects, attribute access): the interpreter alone;
* the ``rsu_imu`` pipeline per epoch of 20-epoch batches with jittered timestamps and the integrity monitor
  (the defaults), as ``bench/filter_step.py`` times it: interpreter plus the compiled kernels;
* the one-pass validation of a 20-epoch batch request (``BatchIn.model_validate_json``): mostly
  pydantic-core's Rust.

Prints each interpreter's minimum over rounds (thread CPU time: other processes' load adds little to it)
and the ratios of the first to the second, with the load average. Each interpreter must have the project
installed (``make`` builds .venv; another venv with ``pip install -e .``); the checkout's own ``service``
is put first on its path, so both run the same code.

    python bench/interpreter_ab.py --python .venv/bin/python --python /tmp/other-venv/bin/python [--rounds 5]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def pure_python_ms() -> float:
    """Thread CPU ms of a loop over dicts, lists and small objects: nothing but the interpreter."""

    class Point:
        __slots__ = ("x", "y")

        def __init__(self, x: int, y: int) -> None:
            self.x, self.y = x, y

    started = time.thread_time()
    table: dict[str, list[Any]] = {}
    for i in range(20000):
        table[str(i)] = [i, i * 2.5, {"a": i}]
    total = 0.0
    for key, value in table.items():
        total += value[1] + len(key)
    points = [Point(i, i + 1) for i in range(20000)]
    total += sum(point.x * point.y for point in points)
    return (time.thread_time() - started) * 1e3


def child(rounds: int) -> dict[str, float]:
    """The three figures' minimums over ``rounds`` in this interpreter."""
    import dataclasses

    import numpy as np
    from edgepos.api.measurement_schemas import BatchIn
    from edgepos.core.compiled import warm_up
    from edgepos.pipelines.base import InitialState
    from edgepos.pipelines.registry import get_pipeline
    from edgepos.sim.scenarios import rsu_imu_paper_scenario
    from edgepos.sim.sensors import environment, rsu_imu_epochs

    sys.path.insert(0, str(ROOT / "bench"))
    from request_parsing import batch_document

    warm_up()
    scenario = rsu_imu_paper_scenario()
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(7))
    env = environment(scenario)
    pipeline = get_pipeline("rsu_imu")
    x0 = scenario.initial_state
    state = pipeline.create(pipeline.resolve_options({}), InitialState(x0[0], x0[3], x0[1], x0[4]))
    for first in range(0, 200, 20):  # a converged state, sent in 20-epoch batches as a vehicle sends them
        _, state = pipeline.process(state, [o for epoch in epochs[first : first + 20] for o in epoch], env)
    rng = np.random.default_rng(11)
    batches = []
    for _ in range(40):  # timestamps jittered by up to +-2 ms: no interval's F and Q from a cache
        shifts = rng.uniform(-0.002, 0.002, 20).tolist()
        batches.append(
            [dataclasses.replace(o, t=o.t + s) for s, epoch in zip(shifts, epochs[200:220]) for o in epoch]
        )
    document = batch_document(20)

    def pipeline_epoch_us() -> float:
        started = time.thread_time()
        for batch in batches:
            pipeline.process(state, batch, env)
        return (time.thread_time() - started) / (len(batches) * 20) * 1e6

    def parse_batch_us() -> float:
        started = time.thread_time()
        for _ in range(200):
            BatchIn.model_validate_json(document)
        return (time.thread_time() - started) / 200 * 1e6

    for function in (pure_python_ms, pipeline_epoch_us, parse_batch_us):
        function()
    return {
        "pure_python_ms": min(pure_python_ms() for _ in range(rounds)),
        "pipeline_epoch_us": min(pipeline_epoch_us() for _ in range(rounds)),
        "parse_batch_us": min(parse_batch_us() for _ in range(rounds)),
    }


def run_child(python: str) -> dict[str, Any]:
    environment = {**os.environ, "PYTHONPATH": str(ROOT / "service")}
    environment.setdefault("NUMBA_CACHE_DIR", str(Path("/tmp") / f"numba-interpreter-ab-{os.getuid()}"))
    result = subprocess.run(
        [python, __file__, "--child"], env=environment, capture_output=True, text=True, check=False
    )
    if result.returncode != 0:
        raise SystemExit(f"{python} failed (is the project installed in its venv?):\n{result.stderr}")
    output = result.stdout
    figures: dict[str, Any] = json.loads(output.strip().splitlines()[-1])
    figures["version"] = subprocess.run(
        [python, "-c", "import sys; print(sys.version.split()[0])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", action="append", default=[], help="a venv's python (give two)")
    parser.add_argument("--rounds", type=int, default=5, help="child runs per interpreter, alternated")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(rounds=5)))
        return 0
    if len(args.python) != 2:
        parser.error("give two interpreters: --python A --python B")
    load_before = os.getloadavg()
    runs: dict[str, list[dict[str, Any]]] = {python: [] for python in args.python}
    for round_index in range(args.rounds):
        order = args.python if round_index % 2 == 0 else args.python[::-1]
        for python in order:
            runs[python].append(run_child(python))
    names = ("pure_python_ms", "pipeline_epoch_us", "parse_batch_us")
    print(
        f"{args.rounds} rounds alternated; load average {load_before[0]:.2f} before, {os.getloadavg()[0]:.2f} after"
    )
    best = {
        python: {name: min(run[name] for run in runs[python]) for name in names} for python in args.python
    }
    print(f"{'interpreter':52} {'pure Python ms':>15} {'pipeline us/epoch':>18} {'parse us/batch':>15}")
    for python in args.python:
        label = f"{python} ({runs[python][0]['version']})"
        print(
            f"{label[:52]:52} "
            + " ".join(f"{best[python][name]:>{w}.2f}" for name, w in zip(names, (15, 18, 15)))
        )
    first, second = args.python
    print(
        f"{'first / second':52} "
        + " ".join(
            f"{best[first][name] / best[second][name]:>{w}.2f}" for name, w in zip(names, (15, 18, 15))
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
