"""Fixtures of the command-line tests: a clean EDGEPOS_* environment, and a real ``edgepos serve`` process
on a free loopback port shared by the tests of a module."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
from edgepos.loadgen.localserver import clean_environment, running, serve_command

ADMIN_KEY = "cli-test-admin-key-0123456789abcdef"


@pytest.fixture(autouse=True)
def _clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """The commands read EDGEPOS_URL and EDGEPOS_ADMIN_KEY: tests set them explicitly, never inherit them."""
    for name in list(os.environ):
        if name.startswith("EDGEPOS_"):
            monkeypatch.delenv(name)


@pytest.fixture(scope="module")
def server_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``edgepos serve`` (one worker, in-process store) with a known admin key."""
    workdir = tmp_path_factory.mktemp("cli-server")
    environment = clean_environment(
        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
        EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
        EDGEPOS_LOG_LEVEL="warning",
    )
    # ready_timeout_s: the server compiles the filter kernels at start-up unless numba's cache has them
    # (over a minute on a busy machine from a fresh clone)
    with running(serve_command(1), environment, workdir / "server.log", ready_timeout_s=300.0) as url:
        yield url


@pytest.fixture
def admin_key() -> str:
    return ADMIN_KEY
