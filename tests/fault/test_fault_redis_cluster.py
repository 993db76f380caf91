"""Two workers on a local Redis Cluster (three primaries, three replicas) under ``edgepos loadtest
--verify``: a plain run, slots migrating while the vehicles stream, and a primary killed with SIGKILL
(its replica promoted), with and without WAIT for one replica.

The vehicles retry a 503 or a dropped connection a bounded number of times (``--retries``), as the
client library does by default; every session is read back afterwards and the acknowledged batches
are counted found or lost. With WAIT 1 an acknowledged batch is on a replica before the vehicle hears
of it, so promoting that replica loses nothing; without WAIT the loss is counted and printed (on
loopback replication usually keeps up, so it is mostly zero, but nothing guarantees it).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest
import redis
from edgepos.loadgen.loadtest import LoadConfig
from faulthelp import ADMIN_KEY, load_with_fault, serve

pytestmark = pytest.mark.slow

VEHICLES = 24
DURATION_S = 14.0
FAULT_AFTER_S = 4.0
RETRIES = 6  # backoff 0.2 s doubling, capped at 5 s: about 6-11 s of retrying in all
PREFIX = "fault:"


def _run(tmp_path, cluster, fault: Callable[[], None] | None, **env: str) -> dict[str, Any]:
    """The load on two workers over ``cluster``; ``fault`` runs FAULT_AFTER_S into it."""
    with serve(tmp_path, 2, EDGEPOS_STORE=cluster.url(PREFIX), EDGEPOS_DEMO_RSUS="true", **env) as server:
        config = LoadConfig(
            url=server.url,
            vehicles=VEHICLES,
            rate=10.0,
            batch=5,
            duration=DURATION_S,
            admin_key=ADMIN_KEY,
            timeout=5.0,
            verify=True,
            retries=RETRIES,
        )
        return load_with_fault(config, lambda elapsed: elapsed >= FAULT_AFTER_S, fault, server).to_json()


def _session_keys(node) -> set[bytes]:
    """The session keys a cluster node holds itself (a plain client: no redirections)."""
    client = redis.Redis(host="127.0.0.1", port=node.port)
    try:
        return set(client.scan_iter(match=f"{PREFIX}*:session:*", count=1000))
    finally:
        client.close()


def _assert_nothing_lost(report: dict[str, Any]) -> None:
    verify = report["verify"]
    assert report["errors"] == 0, (report["errors_by_code"], report["error_samples"])
    assert verify["sessions_checked"] >= VEHICLES
    assert verify["acknowledged_batches"] == verify["found"] > 0
    assert (verify["lost"], verify["mismatches"], verify["unreadable"]) == (0, 0, 0), verify["samples"]


def test_two_workers_on_the_cluster_lose_nothing(tmp_path, cluster_factory):
    cluster = cluster_factory("--save", "", "--appendonly", "no")
    cluster.start()
    report = _run(tmp_path, cluster, None)
    _assert_nothing_lost(report)
    assert report["epochs"] > 0.9 * VEHICLES * 10.0 * DURATION_S * 0.9


def test_slots_migrating_while_vehicles_stream(tmp_path, cluster_factory):
    cluster = cluster_factory("--save", "", "--appendonly", "no")
    cluster.start()
    moved: dict[str, Any] = {}

    def migrate() -> None:
        source, target = cluster.primaries()[:2]
        before = _session_keys(source)
        cluster.reshard(source, target, 2000)  # about 30 of the 256 shards, with their sessions, by MIGRATE
        # the same keys, now on the target: sessions that existed before the migration and went with it
        # (counting the source's keys instead would be fooled by the sessions opened meanwhile)
        moved["before"], moved["keys"] = len(before), before & _session_keys(target)

    report = _run(tmp_path, cluster, migrate)
    _assert_nothing_lost(report)
    print(f"{len(moved['keys'])} of the source's {moved['before']} session keys moved to the target")
    assert moved["keys"], moved  # sessions did move, while the vehicles streamed


@pytest.mark.parametrize("wait_replicas", [1, 0])
def test_a_primary_killed_under_load(tmp_path, cluster_factory, wait_replicas):
    cluster = cluster_factory("--save", "", "--appendonly", "no")
    cluster.start()
    timeline: dict[str, float] = {}

    def kill_a_primary() -> None:
        victim = cluster.primaries()[0]
        victim.kill()  # SIGKILL: whatever it had not replicated is gone with it
        killed = time.monotonic()
        cluster.wait_until_ok(without=victim)  # its replica is promoted
        timeline["failover_s"] = time.monotonic() - killed
        victim.start()  # restarted, as an orchestrator would: it rejoins as the new primary's replica
        cluster.wait_until_ok()
        cluster.wait_until_replicated()

    report = _run(tmp_path, cluster, kill_a_primary, EDGEPOS_REDIS_WAIT_REPLICAS=str(wait_replicas))
    verify = report["verify"]
    print(
        f"WAIT {wait_replicas}: failover {timeline['failover_s']:.1f} s, {verify['acknowledged_batches']} batches "
        f"acknowledged, {verify['found']} found, {verify['lost']} lost, errors after retries {report['errors']}"
        f" {report['errors_by_code']}"
    )
    assert verify["found"] + verify["lost"] == verify["acknowledged_batches"] > 0, verify
    assert verify["mismatches"] == 0 and verify["unreadable"] == 0, verify["samples"]
    if wait_replicas:
        assert verify["lost"] == 0, verify["samples"]
    if verify["lost"] == 0:
        assert report["errors"] == 0, (report["errors_by_code"], report["error_samples"])
    else:  # a vehicle whose session went with the primary is told so (401), and opens a new one
        assert set(report["errors_by_code"]) <= {"unauthorized", "not_found"}, report["errors_by_code"]
