"""Every ``--help`` of the ``edgepos`` command reads as plain text: no reST markup such as double backticks."""

from __future__ import annotations

import argparse

import pytest
from edgepos.cli import COMMANDS, build_parser


def _helps(parser: argparse.ArgumentParser, path: str) -> list[tuple[str, str]]:
    """(command path, help text) of ``parser`` and of every subcommand below it."""
    found = [(path, parser.format_help())]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found.extend(_helps(sub, f"{path} {name}"))
    return found


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help_of_every_command_has_no_rest_markup(command: str | None) -> None:
    helps = _helps(build_parser(command), "edgepos")
    assert len(helps) > len(COMMANDS)  # the subcommands were walked
    for path, text in helps:
        assert "``" not in text, f"{path} --help shows reST markup:\n{text}"
        assert ":func:" not in text and ":class:" not in text, f"{path} --help shows a reST role"
