"""Same-process A/B of the compiled epoch's calls: another tree's ``core/compiled.py`` and
``core/kernels.py`` (loaded under other module names) against this tree's, interleaved.

One epoch as the rsu_imu pipeline runs it (prediction, gate distances, correction of the default
2IMM-CKF bank with 4 RSUs and a gyro, the fix's reads of the result), with the interval jittered by
up to +-2 ms so that no F and Q come from a cache (``--fixed-dt`` for 0.05 s). Both steppers must
give the same numbers; prints each one's minimum and 25th percentile over rounds of 3 x 200 calls.
On a shared machine this separates a microsecond where two processes timed apart do not.

    PYTHONPATH=<this tree>/service python bench/stepper_ab.py --base <other tree>
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import sys
import timeit
from pathlib import Path
from types import ModuleType

import numpy as np
from edgepos.core.compiled import CompiledBankStepper, warm_up
from edgepos.core.imm import InteractingMultipleModel
from edgepos.core.updates import RsuGyroEpoch
from edgepos.pipelines.registry import get_pipeline
from edgepos.pipelines.rsu_imu import _bank, _options_key


def load(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def example_epoch() -> RsuGyroEpoch:
    """Four RSUs beside the road and a gyro reading: the epoch both A/B scripts time (a new one per call,
    as the pipeline builds them)."""
    return RsuGyroEpoch(
        np.array([[0.0, -3.875], [50.0, 3.875], [100.0, -3.875], [-50.0, 3.875]]),
        np.array([[10.4, 0.4], [40.0, -3.0], [90.0, 0.05], [60.0, -3.1]]),
        np.full(4, 0.6),
        np.full(4, 0.01),
        np.array([0.01]),
        0.005,
    )


def example_state(bank: InteractingMultipleModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bank's means, covariances and model probabilities the A/B scripts step from."""
    means, covs = bank.initial(np.array([10.0, 10.0, 0.1, 0.5, 0.2, 0.0, 0.02, 0.01]), np.eye(8) * 0.5)
    return np.ascontiguousarray(means), np.ascontiguousarray(covs), np.array([0.5, 0.3, 0.2])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--base", type=Path, required=True, help="the other tree (a checkout of the repository)"
    )
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--fixed-dt", action="store_true")
    args = parser.parse_args()
    core = args.base / "service" / "edgepos" / "core"
    base_kernels = load("edgepos.core.kernels_ab_base", core / "kernels.py")
    base_compiled = load("edgepos.core.compiled_ab_base", core / "compiled.py")
    warm_up()
    pipeline = get_pipeline("rsu_imu")
    bank = _bank(_options_key(pipeline.resolve_options({})))
    branch = CompiledBankStepper(bank)
    base = base_compiled.CompiledBankStepper(bank)
    base._kernels = base_kernels  # it imports the package's kernels by name: give it its own
    means, covs, probabilities = example_state(bank)
    jitter = np.random.default_rng(1).uniform(-0.002, 0.002, 5000)
    intervals = itertools.cycle([0.05] if args.fixed_dt else (0.05 + jitter).tolist())

    epoch = example_epoch

    def step(stepper, dt: float | None = None):
        measured = epoch()
        prediction = stepper.predict(means, covs, probabilities, next(intervals) if dt is None else dt)
        stepper.gate_distances(prediction.output, measured)
        result = stepper.correct(prediction, measured)
        return (
            float(result.probabilities @ result.nis),
            result.output.mean.tolist(),
            result.output.cov.tolist(),
        )

    if step(base, 0.0503) != step(branch, 0.0503):
        print("the two trees' steps differ")
        return 1
    cases = {"base": lambda: step(base), "this tree": lambda: step(branch), "the epoch object alone": epoch}
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.rounds):
        for name, function in cases.items():
            times[name].append(min(timeit.repeat(function, number=200, repeat=3)) / 200 * 1e6)
    for name, values in times.items():
        print(f"{name:24s} min {min(values):7.2f} us  p25 {np.percentile(values, 25):7.2f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
