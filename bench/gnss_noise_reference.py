"""Measure the adaptive noise level's references on the recording in tests/data/gnss-rover: the level of the
studentised post-fit residuals of gnss_tight's update rows where the noise model holds (the first half,
epochs 0-149), for raw code and for rows with a differential correction from the reference station.

Runs ``edgepos eval gnss-rinex`` (its ``evaluate()``, the CLI's defaults but for the named flags) and
records, at every epoch, the rows the pipeline hands to its noise level (after the screens and RAIM) with
their model variances (pipelines/gnss_correlation.py ``level_inputs``). Per epoch and per kind of row
(all rows, corrected rows only, uncorrected rows only) it takes the estimate the pipeline takes
(gnss/noise_level.py ``epoch_scale``: the median studentised square over its chi-square expectation, one
row of data snooping) of those rows fitted on their own, and prints the redundancy-weighted mean over the
first half, the second half and the whole: the same average the pipeline's memory takes, over the split.
The first-half figures are what ``noise_level_reference`` (raw code, no base: 0.152) and
``noise_level_reference_corrected`` (corrected rows, with ``--base``) hold; the second half is printed for
the report only.

    python bench/gnss_noise_reference.py [--base] [--carrier] [--filter upf|pf|ukf] [--option NAME=JSON ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from edgepos.eval.gnss_rinex import evaluate
from edgepos.eval.overrides import parse_overrides
from edgepos.gnss.noise_level import epoch_scale
from edgepos.pipelines import gnss_tight
from edgepos.pipelines.gnss_correlation import level_inputs

CLI_DEFAULTS = {"particles": 200, "fuzzy": True, "seed": 1}
SPLITS = {"first half (0-149)": (0, 150), "second half (150-299)": (150, 300), "whole": (0, 300)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--filter", default="upf", choices=("upf", "pf", "ukf"))
    parser.add_argument("--base", action="store_true", help="differential corrections from base-0-5min.rnx")
    parser.add_argument("--carrier", action="store_true", help="send the carrier phase (default: raw code)")
    parser.add_argument("--option", action="append", default=[], metavar="NAME=JSON")
    parser.add_argument(
        "--data", type=Path, default=Path(__file__).resolve().parents[1] / "tests/data/gnss-rover"
    )
    args = parser.parse_args()
    records: list[tuple[float, dict[str, tuple[float, int]]]] = []
    original = gnss_tight.noise_level

    def recording(options: Any, level: Any, t: float, dt: float, *rest: Any) -> Any:
        rows, std, smoothing, count, ranges, systems, pseudorange, corrected = rest
        kinds = {"all": np.ones(rows.size, bool)}
        if corrected is not None:
            kinds["corrected"] = corrected[rows]
            kinds["uncorrected"] = ~corrected[rows]
        found = {}
        for kind, member in kinds.items():
            inputs = level_inputs(
                options, dt, rows[member], std, smoothing, count, ranges, systems, pseudorange
            )
            found[kind] = epoch_scale(*inputs)
        records.append((t, found))
        return original(options, level, t, dt, *rest)

    gnss_tight.noise_level = recording  # type: ignore[assignment]
    try:
        evaluate(
            str(args.data / "rover-0-5min.rnx"),
            str(args.data / "broadcast-nav.rnx"),
            str(args.data / "reference-0-5min.csv"),
            options={**CLI_DEFAULTS, **parse_overrides(args.option), "filter": args.filter},
            base_path=str(args.data / "base-0-5min.rnx") if args.base else None,
            carrier=args.carrier,
        )
    finally:
        gnss_tight.noise_level = original
    times = sorted({t for t, _ in records})
    epoch_of = {t: k for k, t in enumerate(times)}
    kinds = sorted({kind for _, found in records for kind in found})
    print(f"{args.filter}, {'base' if args.base else 'no base'}, {'carrier' if args.carrier else 'raw code'}")
    print("| rows | " + " | ".join(SPLITS) + " |")
    print("|---" * (len(SPLITS) + 1) + "|")
    for kind in kinds:
        cells = []
        for first, stop in SPLITS.values():
            pairs = [
                found[kind]
                for t, found in records
                if first <= epoch_of[t] < stop and kind in found and found[kind][1] > 0
            ]
            weights = np.array([r for _, r in pairs], dtype=float)
            values = np.array([e for e, _ in pairs])
            mean = float(weights @ values / weights.sum()) if weights.sum() > 0 else float("nan")
            cells.append(f"{mean:.3f} ({len(pairs)} epochs)")
        print(f"| {kind} | " + " | ".join(cells) + " |")
    flags = " ".join(
        ["--base"] * args.base + ["--carrier"] * args.carrier + [f"--option {o}" for o in args.option]
    )
    print(f"\npython bench/gnss_noise_reference.py --filter {args.filter} {flags}".rstrip())


if __name__ == "__main__":
    main()
