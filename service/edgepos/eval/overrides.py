"""``--option NAME=JSON``: pipeline options an evaluation applies on top of its own, for sensitivity runs."""

from __future__ import annotations

import argparse
import json
from typing import Any


def add_option_argument(parser: argparse.ArgumentParser, example: str) -> None:
    """Add the repeatable ``--option NAME=JSON`` argument (parsed by :func:`parse_overrides`)."""
    parser.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="NAME=JSON",
        help=f"a pipeline option to set, e.g. --option {example} (repeatable)",
    )


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["a=1", "b={\\"c\\": 2}"]`` -> ``{"a": 1, "b": {"c": 2}}``; ValueError names a malformed item."""
    overrides: dict[str, Any] = {}
    for item in items:
        name, separator, value = item.partition("=")
        if not separator or not name.strip():
            raise ValueError(f"--option {item!r}: expected NAME=JSON")
        try:
            overrides[name.strip()] = json.loads(value)
        except json.JSONDecodeError:
            raise ValueError(f"--option {item!r}: the value must be JSON") from None
    return overrides
