"""``edgepos eval EVALUATION``: Monte Carlo evaluations beside the papers' tables.

Each evaluation is one function here that adds its subcommand (common options plus its own) and
points it at the module that runs it; a new evaluation is one such function in ``EVALUATIONS``.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from typing import TYPE_CHECKING

from edgepos.eval import federated, gnss, gnss_rinex, rsu_imu, v2v

#: argparse's object returned by ``add_subparsers`` (private type name, so spelled out here).
if TYPE_CHECKING:  # generic only in the type stubs, not at run time
    Subparsers = argparse._SubParsersAction[argparse.ArgumentParser]


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {value}")
    return value


def _common_options(parser: argparse.ArgumentParser, runs: int) -> None:
    """Options every Monte Carlo evaluation takes."""
    parser.add_argument("--runs", type=_positive_int, default=runs, help=f"Monte Carlo runs (default {runs})")
    parser.add_argument(
        "--seed",
        type=_non_negative_int,
        default=1,
        help="base seed; run r uses numpy default_rng([seed, r]) (default 1)",
    )
    parser.add_argument(
        "--workers",
        type=_positive_int,
        default=os.cpu_count() or 1,
        help="worker processes; results do not depend on it (default: CPU count)",
    )
    parser.add_argument("--json", metavar="FILE", default=None, help="also write the summary as JSON to FILE")
    parser.add_argument(
        "--plots",
        metavar="DIR",
        default=None,
        help="write PNG figures to DIR (needs the edgepos[plots] extra)",
    )


def _rsu_imu(subparsers: Subparsers) -> None:
    help_text = "RSU + IMU paper (2IMM-CKF), sec. 5: Tables 2 and 4, Figs. 6-7 and 10-13"
    parser = subparsers.add_parser("rsu-imu", help=help_text, description=help_text)
    _common_options(parser, runs=200)
    rsu_imu.configure(parser)
    parser.set_defaults(_evaluation=rsu_imu.run)


def _gnss_rinex(subparsers: Subparsers) -> None:
    help_text = "gnss_tight on a real RINEX recording against a reference, beside the WLS baseline"
    parser = subparsers.add_parser("gnss-rinex", help=help_text, description=help_text)
    gnss_rinex.configure(parser)
    parser.set_defaults(_evaluation=gnss_rinex.run)


def _gnss(subparsers: Subparsers) -> None:
    help_text = "GNSS + RISS paper (UPF, fuzzy noise): Table 2 on a simulated street-canyon drive"
    parser = subparsers.add_parser("gnss", help=help_text, description=help_text)
    _common_options(parser, runs=20)
    gnss.configure(parser)
    parser.set_defaults(_evaluation=gnss.run)


def _federated(subparsers: Subparsers) -> None:
    help_text = "V2X federated GPS/DR/V2X paper, sec. 3: Table 1 and Fig. 5 (feedback on/off)"
    parser = subparsers.add_parser("federated", help=help_text, description=help_text)
    _common_options(parser, runs=300)
    federated.configure(parser)
    parser.set_defaults(_evaluation=federated.run)


def _v2v(subparsers: Subparsers) -> None:
    help_text = "V2V TOA cooperative positioning paper, sec. 4: Table 2 (straight and ring)"
    parser = subparsers.add_parser("v2v", help=help_text, description=help_text)
    _common_options(parser, runs=200)
    v2v.configure(parser)
    parser.set_defaults(_evaluation=v2v.run)


#: One function per evaluation, each adding its subcommand.
EVALUATIONS: tuple[Callable[[Subparsers], None], ...] = (_rsu_imu, _v2v, _federated, _gnss, _gnss_rinex)


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the evaluations as sub-subcommands of ``edgepos eval``."""
    subparsers = parser.add_subparsers(dest="evaluation", required=True, metavar="EVALUATION")
    for add in EVALUATIONS:
        add(subparsers)


def run(args: argparse.Namespace) -> int:
    """Run the chosen evaluation; its exit code."""
    return int(args._evaluation(args))
