"""``edgepos loadtest --verify``: every session is read back and must hold exactly what its vehicle
was acknowledged; a disagreement is reported and fails the command."""

from __future__ import annotations

import asyncio
import json

import pytest
from edgepos.cli import main
from edgepos.loadgen.loadtest import Recorder, Vehicle
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos_client import Session
from loadgenhelp import ADMIN_KEY


class Info:
    def __init__(self, last_seq: int, batches: int, epochs: int) -> None:
        self.last_seq, self.batches, self.epochs = last_seq, batches, epochs


class LyingServer:
    """Acknowledges batches but, when ``drops`` is set, holds one batch fewer than it acknowledged."""

    def __init__(self, drops: bool) -> None:
        self.drops = drops
        self.sent = 0

    async def create_session(self, vehicle_id, pipeline="rsu_imu", *, options=None, initial_state=None):
        self.sent = 0
        return Session("s1", "token")

    async def delete_session(self, session) -> None:
        return None

    async def send_batch(self, session, measurements, seq=None, *, include_state=False):
        self.sent += 1
        return [object()] * len(measurements)

    async def get_session(self, session):
        held = self.sent - 1 if self.drops else self.sent
        return Info(held, held, 2 * held)


@pytest.mark.parametrize("drops", [False, True])
def test_verify_compares_the_server_with_what_was_acknowledged(drops: bool) -> None:
    recorder = Recorder()
    vehicle = Vehicle(0, LyingServer(drops), [[None, None]] * 3, rsu_imu_paper_scenario(), recorder, verify=True)  # type: ignore[arg-type, list-item]

    async def drive() -> None:
        for _ in range(4):  # three batches, then a new trip: the first session is checked
            await vehicle.send_one()
        await vehicle.check_session()  # the end of the run checks the live one

    asyncio.run(drive())
    assert recorder.verified == 2
    assert recorder.verify_mismatches == (2 if drops else 0)
    assert bool(recorder.verify_samples) == drops


@pytest.mark.slow
def test_verify_against_a_real_server(server_url: str, tmp_path) -> None:
    out = tmp_path / "load.json"
    argv = ["loadtest", "--url", server_url, "--admin-key", ADMIN_KEY, "--vehicles", "3", "--rate", "20"]
    argv += ["--batch", "10", "--duration", "2", "--verify", "--json", str(out)]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    assert report["errors"] == 0
    assert report["verify"] == {"sessions_checked": 3, "mismatches": 0, "skipped_after_error": 0, "samples": []}
