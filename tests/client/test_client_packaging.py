"""The client installs alone (httpx + pydantic, no server import) and the Docker files are sound."""

from __future__ import annotations

import ast
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"


def test_client_distribution_depends_on_httpx_and_pydantic_only() -> None:
    project = tomllib.loads((ROOT / "client" / "pyproject.toml").read_text())["project"]
    assert project["name"] == "edgepos-client"
    assert sorted(re.split(r"[<>=!~ ]", dep)[0] for dep in project["dependencies"]) == ["httpx", "pydantic"]
    # the batch WebSocket (client.websocket) is an extra, imported only when a socket is made
    assert [re.split(r"[<>=!~ ]", dep)[0] for dep in project["optional-dependencies"]["websocket"]] == [
        "websockets"
    ]
    assert (ROOT / "client" / "edgepos_client" / "py.typed").exists()


def test_client_imports_nothing_from_the_server() -> None:
    for path in (ROOT / "client" / "edgepos_client").glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            assert not any(name == "edgepos" or name.startswith("edgepos.") for name in names), path
    code = "import sys, edgepos_client; print(sorted(m for m in sys.modules if m.split('.')[0] in ('edgepos', 'numpy', 'fastapi', 'websockets')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def _instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of the Dockerfile, continuation lines joined."""
    text = re.sub(r"\\\n", " ", (DOCKER / "Dockerfile").read_text())
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.strip().startswith("#")]
    return [(line.split(None, 1)[0].upper(), line.split(None, 1)[1] if " " in line else "") for line in lines]


def test_dockerfile_shape_and_copied_paths_exist() -> None:
    instructions = _instructions()
    assert instructions[0] == ("FROM", "python:3.11-slim")
    by_kind: dict[str, list[str]] = {}
    for kind, args in instructions:
        by_kind.setdefault(kind, []).append(args)
    for args in by_kind["COPY"]:
        *sources, _destination = shlex.split(args)
        for source in sources:
            assert (ROOT / source).exists(), (
                f"COPY source {source} missing from the build context (repo root)"
            )
    user = by_kind["USER"][-1]
    assert user not in ("root", "0")
    assert "EXPOSE" in by_kind and by_kind["EXPOSE"] == ["8000"]
    assert any("EDGEPOS_WORKERS=" in env for env in by_kind["ENV"])
    assert any("EDGEPOS_PORT=8000" in env for env in by_kind["ENV"])
    cmd = ast.literal_eval(by_kind["CMD"][-1])
    assert cmd == ["edgepos", "serve", "--host", "0.0.0.0"]
    healthcheck = by_kind["HEALTHCHECK"][-1]
    exec_form = ast.literal_eval(healthcheck[healthcheck.index("CMD") + 3 :].strip())
    assert exec_form[:2] == ["python", "-c"] and "/healthz" in exec_form[2]
    compile(exec_form[2], "<healthcheck>", "exec")
    assert "curl" not in healthcheck


def test_compose_runs_the_service_on_its_defaults() -> None:
    yaml = pytest.importorskip("yaml")
    compose = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    ((name, service),) = compose["services"].items()
    assert name == "edgepos"
    build = service["build"]
    assert (DOCKER / build["context"] / build["dockerfile"]).resolve() == (DOCKER / "Dockerfile").resolve()
    assert any(str(port).endswith(":8000") for port in service["ports"])
    environment = service.get("environment", {})
    assert "EDGEPOS_STORE" not in environment and environment.get("EDGEPOS_WORKERS") == "1"
    for volume in service.get("volumes", []):
        assert volume.split(":", 1)[0] in compose.get("volumes", {})
