"""Same-process A/B of the epoch kernels of two git revisions, loaded the same way.

``core/kernels.py`` and ``core/kernels_correct.py`` of each revision are written to a temporary directory
under their own module names (the first importing the second by its new name) and compiled there, so that
neither side runs from the package and its on-disk cache: measured on this host, the same code loaded as
a copy against the package's own ran about 2 us slower per correction, a bias that swamps a small change.
The rounds alternate which side goes first. Prints each side's minimum and quartile of
``predict_epoch`` and ``correct_step`` (one 2IMM-CKF epoch: models CA, AT, Singer; 4 RSUs and a gyro)
and whether the two give the same numbers.

    python bench/kernels_ab.py [--a main] [--b HEAD] [--rounds 15]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import timeit
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from edgepos.core.compiled import CompiledBankStepper, warm_up
from edgepos.pipelines.registry import get_pipeline
from edgepos.pipelines.rsu_imu import _bank, _options_key

sys.path.insert(0, str(Path(__file__).resolve().parent))
from revision_modules import load_revision_modules
from stepper_ab import example_epoch, example_state

FILES = ("kernels", "kernels_correct")


def load_revision(revision: str, tag: str, directory: Path) -> ModuleType:
    """The revision's kernels as module ``kernels_<tag>`` (its correction as ``kernels_correct_<tag>``)."""
    return load_revision_modules(revision, "edgepos.core", FILES, tag, directory)["kernels"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", default="main", help="git revision of side A")
    parser.add_argument("--b", default="HEAD", help="git revision of side B")
    parser.add_argument("--rounds", type=int, default=15)
    args = parser.parse_args()
    warm_up()
    bank = _bank(_options_key(get_pipeline("rsu_imu").resolve_options({})))
    stepper = CompiledBankStepper(bank)
    means, covs, probabilities = example_state(bank)
    measured = example_epoch()
    dt = 0.0503
    predicted = np.empty(stepper._prediction_size)
    corrected = np.empty(stepper._correction_size)
    predict_args: tuple[Any, ...] = (
        means, covs, probabilities, stepper._transition, stepper._active, stepper._common,
        stepper._phi_slot, dt, dt, stepper._motion_kinds, stepper._motion_params, stepper._kinds,
        stepper._filter_kind, stepper._weights, stepper._has_centre, predicted,
    )  # fmt: skip
    correct_args: tuple[Any, ...] = (
        predicted, stepper._active, stepper._common, stepper._phi_slot, stepper._priority, stepper._others,
        *measured.kernel_arrays, measured.gyro_min_speed**2, bool(measured.averaged), stepper._filter_kind,
        stepper._weights, stepper._has_centre, corrected,
    )  # fmt: skip
    with tempfile.TemporaryDirectory() as directory:
        sys.path.insert(0, directory)
        sides = {
            "A": load_revision(args.a, "a", Path(directory)),
            "B": load_revision(args.b, "b", Path(directory)),
        }
        results = {}
        for name, kernels in sides.items():
            kernels.predict_epoch(*predict_args)
            kernels.correct_step(*correct_args)
            results[name] = (predicted.copy(), corrected.copy())
        same = all(np.array_equal(x, y) for x, y in zip(results["A"], results["B"], strict=True))
        largest = max(float(np.max(np.abs(x - y))) for x, y in zip(results["A"], results["B"], strict=True))
        times: dict[tuple[str, str], list[float]] = {
            (kernel, side): [] for kernel in ("predict_epoch", "correct_step") for side in sides
        }
        for round_ in range(args.rounds):
            order = list(sides) if round_ % 2 == 0 else list(reversed(sides))
            for side in order:
                kernels = sides[side]
                for kernel, call in (
                    ("predict_epoch", lambda k=kernels: k.predict_epoch(*predict_args)),
                    ("correct_step", lambda k=kernels: k.correct_step(*correct_args)),
                ):
                    best = min(timeit.repeat(call, number=300, repeat=3)) / 300 * 1e6
                    times[(kernel, side)].append(best)
    print(f"A = {args.a}, B = {args.b}: {'the same numbers' if same else f'differ by up to {largest:.3g}'}")
    for (kernel, side), values in times.items():
        print(f"{kernel:14s} {side}  min {min(values):7.2f} us  p25 {np.percentile(values, 25):7.2f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
