"""The shell and Python examples of the README and the guides, run as written against a live server.

A newcomer pastes them one block after the other into a shell in the repository, next to the
`edgepos-admin.key` that `make serve` writes, with the server on 127.0.0.1:8000. Here the server runs
on a free loopback port (the only change made to the blocks), each page's blocks run in order in one
bash with `set -e`, and no answer may be an error body. `make serve` and `make test` blocks are not run.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from edgepos.loadgen.localserver import clean_environment, running, serve_command

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def shell_blocks(page: Path) -> list[str]:
    """The page's ```sh blocks that talk to the server (those naming localhost:8000 or the admin key)."""
    blocks = re.findall(r"^```sh\n(.*?)^```", page.read_text(encoding="utf-8"), re.DOTALL | re.MULTILINE)
    return [
        block
        for block in blocks
        if ("localhost:8000" in block or "127.0.0.1:8000" in block)
        and not any(line.startswith("make ") for line in block.splitlines())  # the two commands themselves
    ]


def python_blocks(page: Path) -> list[str]:
    """The page's ```python blocks that open a client on 127.0.0.1:8000."""
    blocks = re.findall(r"^```python\n(.*?)^```", page.read_text(encoding="utf-8"), re.DOTALL | re.MULTILINE)
    return [block for block in blocks if "127.0.0.1:8000" in block]


@pytest.fixture
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    """A fresh server per page: each page's tour registers its own vehicles from scratch."""
    workdir = tmp_path_factory.mktemp("docs-examples")
    environment = clean_environment(
        EDGEPOS_ADMIN_KEY_FILE=str(workdir / "edgepos-admin.key"),  # generated, as under make serve
        EDGEPOS_DEMO_RSUS="true",
    )
    with running(serve_command(1), environment, workdir / "server.log", ready_timeout_s=300.0) as url:
        yield url, workdir / "edgepos-admin.key"


def _run(script: str, url: str, key_file: Path, cwd: Path) -> str:
    port = url.rsplit(":", 1)[1]
    script = script.replace("localhost:8000", f"127.0.0.1:{port}").replace(
        "127.0.0.1:8000", f"127.0.0.1:{port}"
    )
    script = script.replace("@tests/data/", f"@{ROOT}/tests/data/")  # the tour runs in the repository
    script = re.sub(
        r"(?<![\w/])\.venv/bin/", f"{Path(sys.executable).parent}/", script
    )  # the repository's venv
    (cwd / "edgepos-admin.key").write_text(key_file.read_text())
    result = subprocess.run(
        ["bash", "-e", "-o", "pipefail", "-c", f"ADMIN=$(cat edgepos-admin.key)\nexport ADMIN\n{script}"],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin", "HOME": str(cwd)},
    )
    assert result.returncode == 0, (
        f"exit {result.returncode}\n{script}\n--- stdout\n{result.stdout}\n--- stderr\n{result.stderr}"
    )
    return result.stdout


def _no_error_bodies(output: str) -> None:
    for line in re.split(r"(?<=\})(?=\{)|\n", output):
        line = line.strip()
        if line.startswith("{"):
            assert '"error":' not in line, line


@pytest.mark.parametrize(
    "page", ["README.md", "docs/getting-started.md", "docs/rsu-imu.md", "docs/v2v.md", "docs/federated.md"]
)
def test_the_pages_examples_run_as_written(page: str, server: tuple[str, Path], tmp_path: Path) -> None:
    url, key_file = server
    path = ROOT / page
    blocks = shell_blocks(path)
    assert blocks, f"{page} has no example talking to the server"
    port = url.rsplit(":", 1)[1]
    runs = []
    for index, block in enumerate(python_blocks(path)):  # after the shell blocks: they export what it reads
        (tmp_path / f"example_{index}.py").write_text(block.replace("127.0.0.1:8000", f"127.0.0.1:{port}"))
        runs.append(f"echo PYTHON-{index}; {sys.executable} example_{index}.py")
    output = _run("\n".join([*blocks, *runs]), url, key_file, tmp_path)
    _no_error_bodies(output)
    assert '"fixes":' in output  # every page's exchange ends with a batch answered
    for index in range(len(runs)):
        printed = output.split(f"PYTHON-{index}\n", 1)[1].split("PYTHON-", 1)[0]
        assert printed.strip(), f"{page}: the Python example printed nothing"


def test_the_tours_answers_are_what_the_readme_shows(server: tuple[str, Path], tmp_path: Path) -> None:
    """The README's tour answers with the fix its comments show (rounded as printed there)."""
    url, key_file = server
    output = _run("\n".join(shell_blocks(ROOT / "README.md")), url, key_file, tmp_path)
    answer = json.loads(output[output.rindex('{"seq":1') :].splitlines()[0])
    fix = answer["fixes"][0]
    assert fix["status"] == "tracking"
    assert round(fix["x"], 2) == 0.56 and round(fix["y"], 2) == -0.02
