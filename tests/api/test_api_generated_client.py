"""A client generated from the committed openapi.json by openapi-python-client (``openapi-python-client
generate --path openapi.json --meta none``) drives one session against the real server process: open it
with the admin key, send a batch with the session's token, read the fix back. Its functions carry the
operations' short ids (create_session, post_batch, get_session)."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_api_server import running_server

pytest.importorskip("openapi_python_client")
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
ADMIN_KEY = "generated-client-admin-key-7e2a51"


def _generate(tmp_path: Path) -> None:
    """Write the package ``edgepos_generated`` under tmp_path (no network: the schema is a local file)."""
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "openapi_python_client",
            "generate",
            "--path",
            str(ROOT / "openapi.json"),
            "--meta",
            "none",
            "--output-path",
            str(tmp_path / "edgepos_generated"),
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
        # its post-generation hook formats the code with ruff (the dev extra's, next to this Python)
        env={**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"},
    )
    assert (tmp_path / "edgepos_generated" / "client.py").exists(), run.stdout + run.stderr
    # Only the two file uploads' text/plain alternative is skipped (application/octet-stream is kept).
    assert "Unable to parse" not in run.stdout + run.stderr, run.stdout + run.stderr


def test_a_generated_client_runs_one_session(tmp_path, monkeypatch):
    _generate(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    generated = importlib.import_module("edgepos_generated")
    create_session = importlib.import_module("edgepos_generated.api.sessions.create_session")
    post_batch = importlib.import_module("edgepos_generated.api.sessions.post_batch")
    get_session = importlib.import_module("edgepos_generated.api.sessions.get_session")
    models = importlib.import_module("edgepos_generated.models")

    with running_server(tmp_path, EDGEPOS_ADMIN_KEY=ADMIN_KEY, EDGEPOS_DEMO_RSUS="true") as (url, _log):
        admin = generated.AuthenticatedClient(base_url=url, token=ADMIN_KEY)
        created = create_session.sync(
            client=admin,
            body=models.SessionCreate(
                vehicle_id="generated-car",
                pipeline=models.SessionCreatePipeline.RSU_IMU,
                initial_state=models.InitialStateIn(x=0.0, y=5.0, vx=10.0, vy=0.0),
            ),
        )
        assert isinstance(created, models.SessionCreated), created
        vehicle = generated.AuthenticatedClient(base_url=url, token=created.token)
        # The vehicle at (0, 5) seen from the demo map's RSUs S+000 (0, -3.875) and N+050 (50, 15.125).
        batch = models.BatchIn(
            seq=1,
            measurements=[
                models.GyroMeasurement(t=0.0, type_="gyro", yaw_rate=0.0),
                models.RsuMeasurement(t=0.0, type_="rsu", rsu_id="S+000", range_=8.875, bearing=1.5708),
                models.RsuMeasurement(t=0.0, type_="rsu", rsu_id="N+050", range_=51.015, bearing=-2.9418),
            ],
        )
        answer = post_batch.sync(created.session_id, client=vehicle, body=batch)
        assert isinstance(answer, models.BatchOut), answer
        assert answer.seq == 1
        assert len(answer.fixes) == 1
        fix = answer.fixes[0]
        assert fix.t == 0.0
        assert abs(fix.x - 0.0) < 5.0 and abs(fix.y - 5.0) < 5.0
        session = get_session.sync(created.session_id, client=vehicle)
        assert isinstance(session, models.SessionOut), session
        assert session.last_seq == 1
        assert session.last_fix is not None and session.last_fix.t == 0.0
