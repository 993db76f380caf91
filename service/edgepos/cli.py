"""The ``edgepos`` command: serve | eval | simulate | loadtest.

Each subcommand lives in its own module exposing ``configure(parser)`` and ``run(args) -> int``;
this file only wires them together.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "serve": ("edgepos.api.serve", "run the edge positioning service"),
    "eval": ("edgepos.eval.commands", "Monte Carlo evaluations beside the papers' tables"),
    "simulate": ("edgepos.loadgen.simulate", "drive a running server with simulated vehicles"),
    "loadtest": ("edgepos.loadgen.loadtest", "load-test a running server (loopback only)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="edgepos", description=__doc__.splitlines()[0])
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        module = importlib.import_module(module_name)
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        module.configure(sub)
        sub.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args._run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
