"""The GNSS accuracy table of docs/gnss.md: every filter with and without Doppler, carrier phase and the
reference station, on the recording in tests/data/gnss-rover, beside the WLS baseline.

Each row is ``edgepos eval gnss-rinex`` (its ``evaluate()``, the defaults but for the named options and
inputs) scored on the first half (epochs 0-149, where settings were chosen), the second half (150-299,
the report split) and the whole five minutes; the command for a cell is printed under the table.
Horizontal RMS (m), the 95th percentile in brackets, and the epochs with a reference but no fix.

    python bench/gnss_rinex_table.py [--filters upf,pf,ukf] [--data tests/data/gnss-rover]
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from typing import Any

from edgepos.eval.gnss_rinex import evaluate

CLI_DEFAULTS = {"particles": 200, "fuzzy": True, "seed": 1}
"""What ``edgepos eval gnss-rinex`` passes besides the filter: a fixed seed, so that every cell reproduces."""
HALVES = {"first half (0-149, choose)": (0, 150), "second half (150-299, report)": (150, 300), "whole": None}
VARIANTS: dict[str, dict[str, Any]] = {
    "code only": {"doppler": False, "carrier": False, "base": False},
    "code + Doppler": {"doppler": True, "carrier": False, "base": False},
    "code + Doppler + phase (Hatch)": {"doppler": True, "carrier": True, "base": False, "mode": "hatch"},
    "code + Doppler + phase (Hatch and TDCP, the default)": {"doppler": True, "carrier": True, "base": False},
    "code + Doppler + phase (TDCP)": {"doppler": True, "carrier": True, "base": False, "mode": "tdcp"},
    "code + Doppler + base": {"doppler": True, "carrier": False, "base": True},
    "code + Doppler + phase (Hatch) + base": {
        "doppler": True,
        "carrier": True,
        "base": True,
        "mode": "hatch",
    },
    "code + Doppler + phase (Hatch and TDCP) + base": {"doppler": True, "carrier": True, "base": True},
    "code + Doppler + phase (TDCP) + base": {"doppler": True, "carrier": True, "base": True, "mode": "tdcp"},
}
"""``mode``: the ``carrier_smoothing`` option when not the default (hatch+tdcp)."""


def _options(filter_name: str, variant: dict[str, Any]) -> dict[str, Any]:
    options = {**CLI_DEFAULTS, "filter": filter_name, "use_doppler": variant["doppler"]}
    if "mode" in variant:
        options["carrier_smoothing"] = variant["mode"]
    return options


def _flags(filter_name: str, variant: dict[str, Any]) -> str:
    flags = [f"--filter {filter_name}"]
    flags += [] if variant["doppler"] else ["--option use_doppler=false"]
    flags += [] if variant["carrier"] else ["--no-carrier"]
    flags += [f"--option 'carrier_smoothing=\"{variant['mode']}\"'"] if "mode" in variant else []
    flags += ["--base $D/base-0-5min.rnx"] if variant["base"] else []
    return " ".join(flags)


def _cell(report: dict[str, Any]) -> str:
    missing = report["reference_epochs_without_fix"]
    figure = f"{report['horizontal_rms_m']:.2f} ({report['horizontal_p95_m']:.2f})"
    return figure if not missing else f"{figure}, {missing} without a fix"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--filters", default="upf,pf,ukf")
    parser.add_argument(
        "--data", type=Path, default=Path(__file__).resolve().parents[1] / "tests/data/gnss-rover"
    )
    args = parser.parse_args()
    files = (
        str(args.data / "rover-0-5min.rnx"),
        str(args.data / "broadcast-nav.rnx"),
        str(args.data / "reference-0-5min.csv"),
    )
    base = str(args.data / "base-0-5min.rnx")
    print("| solution | " + " | ".join(HALVES) + " |")
    print("|---" * (len(HALVES) + 1) + "|")
    baseline: dict[bool, list[str]] = {}
    for filter_name, (name, variant) in itertools.product(args.filters.split(","), VARIANTS.items()):
        cells = []
        for scored in HALVES.values():
            report = evaluate(
                *files,
                options=_options(filter_name, variant),
                score_epochs=scored,
                base_path=base if variant["base"] else None,
                carrier=variant["carrier"],
            )
            cells.append(_cell(report))
            if variant["doppler"] and not variant["carrier"]:
                baseline.setdefault(variant["base"], []).append(_cell(report["baseline"]))
        print(f"| {filter_name.upper()}, {name} | " + " | ".join(cells) + " |")
    for with_base, cells in baseline.items():
        label = "WLS baseline (gnss/spp.py)" + (" + base" if with_base else "")
        print(f"| {label} | " + " | ".join(cells[: len(HALVES)]) + " |")
    print("\nEach cell: D=tests/data/gnss-rover; edgepos eval gnss-rinex --obs $D/rover-0-5min.rnx --nav")
    print(
        "$D/broadcast-nav.rnx --reference $D/reference-0-5min.csv FLAGS [--score-epochs 0:150|150:300], FLAGS:"
    )
    for filter_name, (name, variant) in itertools.product(args.filters.split(","), VARIANTS.items()):
        print(f"  {filter_name.upper()}, {name}: {_flags(filter_name, variant)}")


if __name__ == "__main__":
    main()
