"""Write the app's OpenAPI schema to openapi.json: ``python -m edgepos.api.openapi [PATH]``.

Without PATH it writes the repository's root openapi.json (or ./openapi.json outside a checkout).
The schema comes from an app on default settings, independent of the environment, rendered with
sorted keys, 2-space indent and a trailing newline, so the file changes only when the API does.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from pydantic import SecretStr

_REPO_ROOT = Path(__file__).resolve().parents[3]
DEFAULT_PATH = (_REPO_ROOT if (_REPO_ROOT / "pyproject.toml").exists() else Path.cwd()) / "openapi.json"


def schema() -> dict[str, Any]:
    """The OpenAPI document of an app built on default settings (the admin key is not in it)."""
    from edgepos.api.app import create_app
    from edgepos.api.settings import Settings

    settings = Settings.model_construct(admin_key=SecretStr("schema-only"))
    return create_app(settings).openapi()


def render() -> str:
    return json.dumps(schema(), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m edgepos.api.openapi", description="Write the app's OpenAPI schema."
    )
    parser.add_argument(
        "path", nargs="?", type=Path, default=DEFAULT_PATH, help=f"where to write (default {DEFAULT_PATH})"
    )
    path = parser.parse_args(argv).path
    path.write_text(render(), encoding="utf-8")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
