"""``edgepos serve`` says that it compiles the filter kernels on a first start (tens of seconds with the
port closed otherwise looks like a hang), and how long it took; a warm start says nothing."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
from edgepos.api import serve
from edgepos.core import compiled
from edgepos.loadgen.localserver import clean_environment, running, serve_command


def _fake(monkeypatch: pytest.MonkeyPatch, *, cached: bool, compiled_now: int, cache_dir: str | None) -> None:
    monkeypatch.setattr(compiled, "compiled_enabled", lambda: True)
    monkeypatch.setattr(compiled, "kernels_cached", lambda: cached)
    monkeypatch.setattr(compiled, "kernels_compiled", lambda: compiled_now)
    monkeypatch.setattr(compiled, "kernel_cache_dir", lambda: cache_dir)
    monkeypatch.setattr(compiled, "warm_up", lambda: 12.34)


def test_a_cold_cache_is_announced_on_one_line_with_the_time(monkeypatch: pytest.MonkeyPatch) -> None:
    _fake(monkeypatch, cached=False, compiled_now=43, cache_dir="/var/cache/edgepos/numba")
    stream = io.StringIO()
    assert serve.warm_up_kernels(stream) == 12.34
    text = stream.getvalue()
    assert text.count("\n") == 1 and text.endswith(" done in 12.3 s\n")
    assert "compiling the filter kernels the first time" in text and "/var/cache/edgepos/numba" in text


def test_no_cache_directory_is_named_as_the_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    _fake(monkeypatch, cached=False, compiled_now=43, cache_dir=None)
    stream = io.StringIO()
    serve.warm_up_kernels(stream)
    assert "every start compiles; set NUMBA_CACHE_DIR" in stream.getvalue()


def test_a_warm_cache_says_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    _fake(monkeypatch, cached=True, compiled_now=0, cache_dir="/c")
    stream = io.StringIO()
    serve.warm_up_kernels(stream)
    assert stream.getvalue() == ""


def test_a_stale_cache_that_compiled_anyway_says_so_after(monkeypatch: pytest.MonkeyPatch) -> None:
    _fake(monkeypatch, cached=True, compiled_now=5, cache_dir="/c")
    stream = io.StringIO()
    serve.warm_up_kernels(stream)
    assert stream.getvalue() == (
        "edgepos serve: compiled the filter kernels again (numba's cache was stale) in 12.3 s\n"
    )


def test_an_empty_cache_directory_is_cold(tmp_path: Path) -> None:
    """Checked in a child with its own NUMBA_CACHE_DIR: importing the kernels compiles nothing."""
    script = (
        "from edgepos.core.compiled import kernel_cache_dir, kernels_cached; "
        "print(kernels_cached(), kernel_cache_dir())"
    )
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "EDGEPOS_NUMBA": "1"}
    done = subprocess.run(
        [sys.executable, "-c", script], env=environment, capture_output=True, text=True, check=True
    )
    cached, directory = done.stdout.split()
    assert cached == "False" and directory.startswith(str(tmp_path))


def test_after_warm_up_every_kernel_is_in_the_cache() -> None:
    compiled.warm_up()  # compiles only when this machine's cache is cold (as tests/core do)
    assert compiled.kernels_cached()


@pytest.mark.slow
def test_a_first_start_prints_the_line_before_the_port_opens(tmp_path: Path) -> None:
    """A real ``edgepos serve`` on a fresh numba cache directory: it compiles, says so, then serves."""
    environment = clean_environment(
        EDGEPOS_ADMIN_KEY="warm-up-test-admin-key-0123456789",
        EDGEPOS_LOG_LEVEL="warning",
        NUMBA_CACHE_DIR=str(tmp_path / "numba"),
    )
    log = tmp_path / "server.log"
    with running(serve_command(1), environment, log, ready_timeout_s=300.0):
        lines = [line for line in log.read_text().splitlines() if "filter kernels" in line]
    assert len(lines) == 1
    assert "compiling the filter kernels the first time" in lines[0] and " done in " in lines[0]
    assert str(tmp_path / "numba") in lines[0]
    # every kernel was compiled and cached by the warm-up, none left for a request to compile: checked on
    # the fresh directory, where no earlier test or run can have cached one
    indexed = {path.name.split("-")[0] for path in (tmp_path / "numba").rglob("*.nbi")}
    kernels = {
        f"{Path(d.py_func.__code__.co_filename).stem}.{d.py_func.__qualname__}"
        for d in compiled._kernel_dispatchers()
    }
    assert kernels - indexed == set()


def test_the_documented_line_is_the_one_printed(monkeypatch: pytest.MonkeyPatch) -> None:
    _fake(monkeypatch, cached=False, compiled_now=43, cache_dir="/c")
    stream = io.StringIO()
    serve.warm_up_kernels(stream)
    printed = stream.getvalue()
    documented = next(
        line
        for line in (Path(__file__).resolve().parents[2] / "docs" / "service.md").read_text().splitlines()
        if line.startswith("edgepos serve: compiling")
    )
    assert printed.split("(")[0] == documented.split("(")[0]
    assert printed.split(";", 1)[1].split(" done in ")[0] == documented.split(";", 1)[1].split(" done in ")[0]
