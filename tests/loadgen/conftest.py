"""A real server process on a free loopback port, shared by the load generator tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from edgepos.loadgen.localserver import clean_environment, running, serve_command
from loadgenhelp import ADMIN_KEY


@pytest.fixture(scope="session")
def server_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``edgepos serve`` (one worker, in-process store) with a known admin key."""
    workdir = tmp_path_factory.mktemp("loadgen-server")
    environment = clean_environment(
        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
        EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
        EDGEPOS_LOG_LEVEL="warning",
    )
    # ready_timeout_s: the server compiles the filter kernels at start-up unless numba's cache has them
    # (over a minute on a busy machine from a fresh clone)
    with running(serve_command(1), environment, workdir / "server.log", ready_timeout_s=300.0) as url:
        yield url
