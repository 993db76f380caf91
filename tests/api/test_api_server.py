"""The real server process on a loopback port, driven over a real socket with plain httpx."""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from apihelp import batch_body, rsu_payload
from edgepos.api import serve

pytestmark = pytest.mark.slow


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextlib.contextmanager
def running_server(tmp_path: Path, *args: str, **env: str) -> Iterator[tuple[str, Path]]:
    """Start ``edgepos serve`` (``python -m edgepos.cli``) on a free loopback port; yields URL and log."""
    port = _free_port()
    environment = {k: v for k, v in os.environ.items() if not k.startswith("EDGEPOS_")}
    environment.update({"EDGEPOS_ADMIN_KEY_FILE": str(tmp_path / "admin.key"), **env})
    log_path = tmp_path / f"server-{port}.log"
    with open(log_path, "wb") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "edgepos.cli", "serve", "--host", "127.0.0.1", "--port", str(port), *args],
            env=environment,
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=tmp_path,
        )
    url = f"http://127.0.0.1:{port}"
    try:
        # A worker compiles the filter kernels at start-up unless numba's cache has them: over a minute
        # on a busy 2-core machine from a fresh clone.
        deadline = time.monotonic() + 300.0
        while True:
            assert process.poll() is None, log_path.read_text()
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                    break
            assert time.monotonic() < deadline, "server did not become ready"
            time.sleep(0.1)
        yield url, log_path
    finally:
        process.terminate()
        try:
            process.wait(timeout=20.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def test_real_server_with_generated_admin_key(tmp_path):
    with running_server(tmp_path) as (url, log_path):
        key_file = tmp_path / "admin.key"
        key = key_file.read_text().strip()
        assert stat.S_IMODE(os.stat(key_file).st_mode) == 0o600
        admin = {"Authorization": f"Bearer {key}"}
        with httpx.Client(base_url=url, timeout=10.0) as client:
            assert client.put("/v1/rsus", json=rsu_payload(), headers=admin).json() == {
                "upserted": len(rsu_payload()["rsus"])
            }
            created = client.post("/v1/sessions", json={"vehicle_id": "socket-car"}, headers=admin)
            assert created.status_code == 201
            session_id = created.json()["session_id"]
            token = {"Authorization": f"Bearer {created.json()['token']}"}
            first = client.post(
                f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 10), headers=token
            )
            assert first.status_code == 200 and len(first.json()["fixes"]) == 10
            retry = client.post(
                f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 10), headers=token
            )
            assert retry.content == first.content
            second = client.post(
                f"/v1/sessions/{session_id}/batches", json=batch_body(2, 10, 10), headers=token
            )
            assert second.status_code == 200
            info = client.get(f"/v1/sessions/{session_id}", headers=token).json()
            assert (info["last_seq"], info["batches"], info["epochs"]) == (2, 2, 20)
            assert info["last_fix"] == {**second.json()["fixes"][-1], "state": None}
            assert client.get("/v1/sessions/" + session_id).status_code == 401
            assert "edgepos_epochs_processed_total 20.0" in client.get("/metrics").text
            assert client.get("/docs").status_code == 200
            assert client.delete(f"/v1/sessions/{session_id}", headers=token).status_code == 204
    log = log_path.read_text()
    assert log.count(key) == 1  # printed once at start-up, never logged
    assert created.json()["token"].split(".", 1)[1] not in log


def test_two_workers_share_sessions_through_sqlite(tmp_path):
    key = "two-worker-admin-key-0123456789"
    admin = {"Authorization": f"Bearer {key}"}
    database = tmp_path / "edgepos.db"
    batches = 12
    with running_server(
        tmp_path, "--workers", "2", EDGEPOS_STORE=f"sqlite:///{database}", EDGEPOS_ADMIN_KEY=key
    ) as (url, _):
        with httpx.Client(base_url=url, timeout=10.0) as client:
            client.put("/v1/rsus", json=rsu_payload(), headers=admin)
            created = client.post("/v1/sessions", json={"vehicle_id": "shared"}, headers=admin).json()
        session_id = created["session_id"]
        token = {"Authorization": f"Bearer {created['token']}"}
        bodies = {seq: batch_body(seq, 2 * (seq - 1), 2) for seq in range(1, batches + 1)}
        answers: dict[int, set[bytes]] = {seq: set() for seq in bodies}
        failures: list[str] = []

        def vehicle() -> None:
            # every thread sends every batch; whichever arrives first applies it, the other is a replay
            with httpx.Client(base_url=url, timeout=10.0) as client:
                for seq, body in bodies.items():
                    for _ in range(200):
                        response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token)
                        if response.status_code == 200:
                            answers[seq].add(response.content)
                            break
                        if response.status_code != 409:
                            failures.append(response.text)
                            return
                        last = client.get(f"/v1/sessions/{session_id}", headers=token).json()["last_seq"]
                        if last > seq:
                            break  # the other thread already went past this batch
                        time.sleep(0.01)

        threads = [threading.Thread(target=vehicle) for _ in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120.0)
        assert failures == []
        assert all(
            len(found) == 1 for found in answers.values() if found
        )  # every answer to a seq is the same
        with httpx.Client(base_url=url, timeout=10.0) as client:
            info = client.get(f"/v1/sessions/{session_id}", headers=admin).json()
    assert (info["last_seq"], info["batches"], info["epochs"]) == (batches, batches, 2 * batches)


def _serve_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    serve.configure(parser)
    return parser.parse_args(argv)


def test_several_workers_need_a_shared_store(monkeypatch, capsys):
    monkeypatch.delenv("EDGEPOS_STORE", raising=False)
    assert serve.run(_serve_args("--workers", "2")) == 2
    message = capsys.readouterr().err
    assert "EDGEPOS_STORE=redis://" in message and "sqlite:///" in message


def test_invalid_configuration_is_reported(monkeypatch, capsys):
    monkeypatch.setenv("EDGEPOS_MAX_SESSIONS", "-3")
    assert serve.run(_serve_args()) == 2
    assert "max_sessions" in capsys.readouterr().err


def test_serve_refuses_auth_off_unless_declared_a_lab(tmp_path):
    environment = {k: v for k, v in os.environ.items() if not k.startswith("EDGEPOS_")}
    environment.update({"EDGEPOS_AUTH": "off", "EDGEPOS_ADMIN_KEY_FILE": str(tmp_path / "admin.key")})
    refused = subprocess.run(
        [sys.executable, "-m", "edgepos.cli", "serve", "--port", str(_free_port())],
        check=False,  # the exit status is what the test asserts
        env=environment,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert refused.returncode == 2
    assert "EDGEPOS_LAB=true" in refused.stderr and "--lab" in refused.stderr


def test_lab_server_with_auth_off_is_open_and_says_so(tmp_path):
    with (
        running_server(tmp_path, "--lab", EDGEPOS_AUTH="off") as (url, log_path),
        httpx.Client(base_url=url, timeout=10.0) as client,
    ):
        assert client.put("/v1/rsus", json=rsu_payload()).status_code == 200
        session_id = client.post("/v1/sessions", json={"vehicle_id": "lab-car"}).json()["session_id"]
        answer = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 3))
        assert answer.status_code == 200 and len(answer.json()["fixes"]) == 3
    log = log_path.read_text()
    assert "AUTHENTICATION IS OFF" in log and "authentication is off" in log
