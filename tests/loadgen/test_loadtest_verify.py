"""``edgepos loadtest --verify``: every session is read back and must hold exactly what its vehicle
was acknowledged; a disagreement is reported and fails the command."""

from __future__ import annotations

import asyncio
import json

import pytest
from edgepos.cli import main
from edgepos.loadgen.loadtest import Recorder, Vehicle
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos_client import EdgeposError, Session
from loadgenhelp import ADMIN_KEY


class Info:
    def __init__(self, last_seq: int, batches: int, epochs: int) -> None:
        self.last_seq, self.batches, self.epochs = last_seq, batches, epochs


class Measurement:
    def __init__(self, t: float) -> None:
        self.t = t


class LyingServer:
    """Acknowledges batches but, when ``drops`` is set, holds one batch fewer than it acknowledged; with
    ``fails`` the third batch of a trip gets a 503 (``applied``: after the server stored it), and with
    ``gone`` a session read back is 404."""

    def __init__(
        self, drops: bool = False, fails: bool = False, applied: bool = False, gone: bool = False
    ) -> None:
        self.drops, self.fails, self.applied, self.gone = drops, fails, applied, gone
        self.stored = 0
        self.trips = 0

    async def create_session(self, vehicle_id, pipeline="rsu_imu", *, options=None, initial_state=None):
        self.stored = 0
        self.trips += 1
        return Session(f"s{self.trips}", "token")

    async def delete_session(self, session) -> None:
        return None

    async def send_batch(self, session, measurements, seq=None, *, include_state=False):
        if self.fails and self.stored == 2:
            self.stored += self.applied
            raise EdgeposError("unavailable", "the session store is unavailable", status=503)
        self.stored += 1
        return [object()] * len({m.t for m in measurements})

    async def get_session(self, session):
        if self.gone:
            raise EdgeposError("not_found", "no such session", status=404)
        held = self.stored - 1 if self.drops else self.stored
        return Info(held, held, 2 * held)


BATCHES = [[Measurement(2.0 * k), Measurement(2.0 * k + 1.0)] for k in range(3)]  # two epochs each


def drive(server: LyingServer, sends: int = 4) -> Recorder:
    recorder = Recorder()
    vehicle = Vehicle(0, server, BATCHES, rsu_imu_paper_scenario(), recorder, verify=True)  # type: ignore[arg-type]  # a stand-in client

    async def go() -> None:
        for _ in range(sends):  # three batches, then a new trip: the first session is checked
            await vehicle.send_one()
        await vehicle.check_session()  # the end of the run checks the live one

    asyncio.run(go())
    return recorder


@pytest.mark.parametrize("drops", [False, True])
def test_verify_counts_acknowledged_batches_found_and_lost(drops: bool) -> None:
    tally = drive(LyingServer(drops=drops)).verify
    assert (tally.sessions, tally.acknowledged) == (2, 4)  # 3 in the first trip, 1 in the second
    assert (tally.found, tally.lost) == ((2, 2) if drops else (4, 0))
    assert tally.inconsistent == 0 and tally.failed == drops
    assert bool(tally.samples) == drops


@pytest.mark.parametrize("applied", [False, True])
def test_a_session_that_saw_an_error_is_checked_too(applied: bool) -> None:
    tally = drive(LyingServer(fails=True, applied=applied)).verify
    # trip 1: two acknowledged, the third a 503 (stored or not: both consistent); trip 2: one acknowledged
    assert (tally.sessions, tally.acknowledged, tally.found, tally.lost, tally.inconsistent) == (
        2,
        3,
        3,
        0,
        0,
    )


def test_a_session_that_is_gone_lost_everything_it_was_acknowledged() -> None:
    tally = drive(LyingServer(gone=True)).verify
    assert (tally.sessions, tally.acknowledged, tally.found, tally.lost, tally.sessions_gone) == (
        2,
        4,
        0,
        4,
        2,
    )
    assert tally.failed


@pytest.mark.slow
def test_verify_against_a_real_server(server_url: str, tmp_path) -> None:
    out = tmp_path / "load.json"
    argv = ["loadtest", "--url", server_url, "--admin-key", ADMIN_KEY, "--vehicles", "3", "--rate", "20"]
    argv += ["--batch", "10", "--duration", "2", "--verify", "--json", str(out)]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    assert report["errors"] == 0
    verify = report["verify"]
    assert verify["sessions_checked"] == 3 and verify["acknowledged_batches"] == verify["found"] > 0
    assert (verify["lost"], verify["loss_window_s"], verify["mismatches"], verify["unreadable"]) == (
        0,
        None,
        0,
        0,
    )
