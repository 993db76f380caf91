"""Redis killed for a few seconds under ``edgepos loadtest --verify`` (two workers): every session is
read back afterwards, those that saw the outage included, and the report counts the acknowledged
batches found and lost.

With the append-only file fsynced on every write nothing acknowledged is lost; with no persistence
the restarted Redis is empty and every batch acknowledged before the kill is counted as lost, with
the window of the run over which they were acknowledged. Either way the vehicles saw clear errors
(503), not hangs, and the service opened new sessions again by itself once Redis was back.
"""

from __future__ import annotations

import time

import pytest
from edgepos.loadgen.loadtest import LoadConfig
from faulthelp import ADMIN_KEY, load_with_fault, serve

pytestmark = pytest.mark.slow

VEHICLES = 20
DURATION_S = 12.0
#: Redis is killed this long after the load started (and only once it holds sessions), and stays down this long.
KILL_AFTER_S = 3.0
OUTAGE_S = 3.0


def _run_with_outage(tmp_path, redis) -> tuple[dict, float]:
    """The load with Redis killed during it; returns the report and how long after the start Redis was killed (s)."""
    store_url = redis.url("verify:", socket_timeout="0.5", socket_connect_timeout="0.5")
    with serve(tmp_path, 2, EDGEPOS_STORE=store_url, EDGEPOS_DEMO_RSUS="true") as server:
        config = LoadConfig(
            url=server.url,
            vehicles=VEHICLES,
            rate=10.0,
            batch=5,
            duration=DURATION_S,
            admin_key=ADMIN_KEY,
            timeout=5.0,
            verify=True,
        )
        timeline: dict[str, float] = {}

        def holds_sessions(elapsed: float) -> bool:
            timeline["elapsed"] = elapsed
            return elapsed >= KILL_AFTER_S and redis.command("KEYS", "verify:*session*").count(b"$") > 0

        def outage() -> None:
            redis.kill()
            timeline["killed"] = timeline["elapsed"]
            time.sleep(OUTAGE_S)
            redis.start()  # same port, same directory

        report = load_with_fault(config, holds_sessions, outage, server, timeout_s=120.0)
    return report.to_json(), timeline["killed"]


def test_with_aof_always_no_acknowledged_batch_is_lost(tmp_path, redis_factory):
    redis = redis_factory("--appendonly", "yes", "--appendfsync", "always", "--save", "")
    redis.start()
    report, _ = _run_with_outage(tmp_path, redis)
    verify = report["verify"]
    assert report["errors_by_code"].get("unavailable", 0) > 0, report["errors_by_code"]  # clear 503s
    assert report["trips"]["started"] > 0  # sessions opened again after the outage, by the same service
    assert verify["sessions_checked"] >= VEHICLES  # every session, those that saw the outage included
    assert verify["acknowledged_batches"] == verify["found"] > 0
    assert (verify["lost"], verify["mismatches"], verify["unreadable"]) == (0, 0, 0), verify["samples"]


def test_without_persistence_the_lost_batches_are_counted(tmp_path, redis_factory):
    redis = redis_factory("--appendonly", "no", "--save", "")
    redis.start()
    report, killed = _run_with_outage(tmp_path, redis)
    verify = report["verify"]
    assert report["errors_by_code"].get("unavailable", 0) > 0, report["errors_by_code"]
    assert verify["lost"] > 0 and verify["sessions_gone"] > 0, verify
    assert verify["found"] + verify["lost"] == verify["acknowledged_batches"]
    # what was lost was acknowledged before the kill (the restarted Redis is empty, nothing after it is lost)
    assert (
        0 <= verify["loss_started_s"] and verify["loss_started_s"] + verify["loss_window_s"] <= killed + 0.5
    )
    assert verify["mismatches"] == 0 and verify["unreadable"] == 0, verify["samples"]
