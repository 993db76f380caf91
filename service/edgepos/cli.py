"""The ``edgepos`` command: serve | eval | simulate | loadtest | vehicles.

Each subcommand lives in its own module exposing ``configure(parser)`` and ``run(args) -> int``;
this file only wires them together, importing just the module of the subcommand being run so that
``edgepos eval`` never loads the web stack and ``edgepos serve`` never loads the evaluation code.
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
    "loadtest": (
        "edgepos.loadgen.loadtest",
        "load-test a running server (loopback only unless --allow-remote)",
    ),
    "vehicles": ("edgepos.cli_vehicles", "manage a running server's vehicle registry (admin key)"),
}


def plain(text: str) -> str:
    """A docstring's reST as the plain text of a --help: ``edgepos`` reads edgepos."""
    return text.replace("``", "")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported and configured (none for top-level help)."""
    parser = argparse.ArgumentParser(prog="edgepos", description=plain(__doc__.splitlines()[0]))
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        if command == name:
            module = importlib.import_module(module_name)
            module.configure(sub)
            sub.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((arg for arg in argv if arg in COMMANDS), None)
    args = build_parser(command).parse_args(argv)
    return int(args._run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
