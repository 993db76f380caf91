"""How honest gnss_tight's fix covariance is on the recording in tests/data/gnss-rover (issue 21's
consistency target, mean NEES 1-4 with 2 dof): every filter with and without the carrier phase, scored on
the first half (epochs 0-149, where settings are chosen), the second half (150-299, the report split) and
the whole five minutes.

Each cell is ``edgepos eval gnss-rinex`` (its ``evaluate()``, the CLI's defaults but for the named options)
and gives the horizontal RMS (m), the mean NEES of the fix's own horizontal covariance, the fraction of
epochs beyond the 99.9 % bound, the worst 30-epoch mean NEES, and the integrity block's misleading count
and median protection level.

    python bench/gnss_nees_table.py [--filters upf,pf,ukf] [--carrier both|on|off] [--option NAME=JSON ...]
        [--integrity] [--base]

``--option 'noise_level="model"'`` gives the figures before the adaptive noise level (docs/gnss.md).
``--integrity`` prints instead the integrity block of each cell (misleading and hazardous epochs,
availability at the alert limit, median protection level, the largest error over protection level, the
monitor's exclusions). ``--base`` adds differential corrections from the recording's reference station
(tests/data/gnss-rover/base-0-5min.rnx, ``eval gnss-rinex --base``).
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from typing import Any

from edgepos.eval.gnss_rinex import evaluate
from edgepos.eval.overrides import parse_overrides

CLI_DEFAULTS = {"particles": 200, "fuzzy": True, "seed": 1}
"""What ``edgepos eval gnss-rinex`` passes besides the filter: a fixed seed, so that every cell reproduces."""
HALVES = {"first half (0-149)": (0, 150), "second half (150-299)": (150, 300), "whole": None}
CARRIER = {"both": (True, False), "on": (True,), "off": (False,)}


def _cell(report: dict[str, Any], integrity: bool = False) -> str:
    block = report["integrity"]
    if integrity:
        return (
            f"{block['epochs']} epochs: misleading {block['misleading']}, hazardous {block['hazardous']}, "
            f"availability {block['availability']:.3f}, median PL {block['median_protection_level_m']:.1f} m, "
            f"largest error/PL {block['max_error_over_protection_level']:.2f}, detections {block['detections']}"
        )
    return (
        f"{report['horizontal_rms_m']:.2f} m, NEES {block['mean_nees']:.2f} "
        f"({100 * block['beyond_999_fraction']:.1f} %, worst {block['worst_window_mean_nees']:.1f}), "
        f"misleading {block['misleading']}, PL {block['median_protection_level_m']:.1f} m"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--filters", default="upf,pf,ukf")
    parser.add_argument("--carrier", default="both", choices=tuple(CARRIER))
    parser.add_argument("--option", action="append", default=[], metavar="NAME=JSON")
    parser.add_argument(
        "--integrity", action="store_true", help="the integrity block's counts instead of RMS and NEES"
    )
    parser.add_argument(
        "--base", action="store_true", help="differential corrections from the reference station's file"
    )
    parser.add_argument(
        "--data", type=Path, default=Path(__file__).resolve().parents[1] / "tests/data/gnss-rover"
    )
    args = parser.parse_args()
    overrides = parse_overrides(args.option)
    files = (
        str(args.data / "rover-0-5min.rnx"),
        str(args.data / "broadcast-nav.rnx"),
        str(args.data / "reference-0-5min.csv"),
    )
    print("| filter | " + " | ".join(HALVES) + " |")
    print("|---" * (len(HALVES) + 1) + "|")
    for filter_name, carrier in itertools.product(args.filters.split(","), CARRIER[args.carrier]):
        cells = [
            _cell(
                evaluate(
                    *files,
                    options={**CLI_DEFAULTS, **overrides, "filter": filter_name},
                    score_epochs=scored,
                    carrier=carrier,
                    base_path=str(args.data / "base-0-5min.rnx") if args.base else None,
                ),
                args.integrity,
            )
            for scored in HALVES.values()
        ]
        label = (
            f"{filter_name.upper()}"
            + ("" if carrier else ", --no-carrier")
            + (", --base" if args.base else "")
        )
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)
    flags = " ".join(f"--option {o}" for o in args.option)
    print(
        "\nEach cell: D=tests/data/gnss-rover; edgepos eval gnss-rinex --obs $D/rover-0-5min.rnx --nav "
        "$D/broadcast-nav.rnx --reference $D/reference-0-5min.csv --filter F [--no-carrier] "
        f"[--score-epochs 0:150|150:300] {'--base $D/base-0-5min.rnx ' if args.base else ''}{flags}".rstrip()
    )


if __name__ == "__main__":
    main()
