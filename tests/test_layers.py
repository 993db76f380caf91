"""The layer rules of docs/architecture.md, held by the imports themselves (every import statement, also
those inside functions): the estimation packages never reach up into the service."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "service" / "edgepos"

#: package -> the edgepos packages it may import (itself included)
ALLOWED = {
    "core": {"core", "gnss"},
    "gnss": {"core", "gnss"},
    "pipelines": {"core", "gnss", "pipelines"},
    "sim": {"core", "gnss", "pipelines", "sim"},
    "store": {"pipelines", "store"},
    # the commands' implementations, beside the service; cli_output is their --json/--plots helper
    "eval": {"core", "gnss", "pipelines", "sim", "eval", "cli_output"},
    "loadgen": {"core", "gnss", "pipelines", "sim", "loadgen", "cli_output"},
}
#: third-party packages of the web layer, which the estimation packages must not import
WEB = {"fastapi", "starlette", "uvicorn", "httpx", "redis", "pydantic", "pydantic_settings", "websockets"}
ESTIMATION = ("core", "gnss", "pipelines", "sim")


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_a_package_imports_only_the_layers_below_it(package: str) -> None:
    offending = []
    for path in sorted((PACKAGE / package).rglob("*.py")):
        for name in _imports(path):
            parts = name.split(".")
            if parts[0] == "edgepos" and len(parts) > 1 and parts[1] not in ALLOWED[package]:
                offending.append(f"{path.relative_to(PACKAGE)}: {name}")
            if package in ESTIMATION and parts[0] in WEB:
                offending.append(f"{path.relative_to(PACKAGE)}: {name} (web layer)")
    assert not offending, "imports across the layers:\n" + "\n".join(offending)


def test_the_rule_catches_an_upward_import(tmp_path: Path) -> None:
    module = tmp_path / "bad.py"
    module.write_text("def f():\n    from edgepos.api import app\n    import fastapi\n")
    assert {"edgepos.api", "fastapi"} <= _imports(module)
