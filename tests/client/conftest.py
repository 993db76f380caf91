"""Fixtures of the client tests: the real app in-process (through httpx.ASGITransport) and a real
server process on a free loopback port."""

from __future__ import annotations

import os
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import httpx
import pytest
from clienthelp import ADMIN_KEY, make_app, scenario_rsus
from edgepos.loadgen.localserver import clean_environment, running, serve_command
from edgepos_client import AsyncEdgeposClient


@pytest.fixture(autouse=True)
def _clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tests configure the service explicitly, never from the caller's EDGEPOS_* variables."""
    for name in list(os.environ):
        if name.startswith("EDGEPOS_"):
            monkeypatch.delenv(name)


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


@pytest.fixture
async def aclient(tmp_path: Path) -> AsyncIterator[AsyncEdgeposClient]:
    """An async client of a fresh in-process app with the paper scenario's RSUs loaded."""
    transport = httpx.ASGITransport(app=make_app(tmp_path))
    async with AsyncEdgeposClient(
        "http://edgepos.test", ADMIN_KEY, transport=transport, backoff=0.0
    ) as client:
        await client.put_rsus(scenario_rsus())
        yield client


@pytest.fixture(scope="session")
def server_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real ``edgepos serve`` process on a free loopback port (one worker, in-process store)."""
    workdir = tmp_path_factory.mktemp("client-server")
    environment = clean_environment(
        EDGEPOS_ADMIN_KEY=ADMIN_KEY, EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key")
    )
    # ready_timeout_s: the server compiles the filter kernels at start-up unless numba's cache has them
    # (over a minute on a busy machine from a fresh clone)
    with running(serve_command(1), environment, workdir / "server.log", ready_timeout_s=300.0) as url:
        yield url
