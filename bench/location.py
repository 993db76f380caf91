"""Benchmark: the MEC 013 location adapter on a real server.

Starts ``edgepos serve`` (``--workers`` workers; ``--store redis`` starts ``redis-server`` on a free loopback
port, ``memory`` needs one worker) with a site origin, loads the paper scenario's RSU map and one zone
(a 15 m circle about x = 90 m, which the scenario's vehicle reaches around t = 7.5 s), and opens
``--vehicles`` sessions, each located by one batch of the scenario's first 20 epochs (x ~ 10 m). Then:

* the latency of ``GET /location/v3/queries/users`` (every vehicle), of the same for one address, and of
  ``GET /location/v3/queries/zones`` (``--queries`` calls each, sequential, one connection);
* with a zone subscription (every vehicle) whose callback is a receiver in this process on 127.0.0.1:
  ``--crossings`` vehicles in turn send the batch that takes them into the zone; printed is the delay
  from the batch's answer to the notification's arrival (the notifier polls every ``--poll`` s);
* the service's CPU seconds (its processes, from /proc) over ``--idle`` s with that subscription and no
  traffic: what the notifier's polling of every vehicle's latest fix costs.

Loopback only.

    python bench/location.py [--vehicles N] [--poll S] [--crossings K] [--queries Q] [--idle S]
        [--store memory|redis] [--workers W]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from edgepos.core.observations import GyroObservation, RsuObservation
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command, service_cpu_s
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs

ADMIN_KEY = "location-admin-key-" + os.urandom(8).hex()
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
SCENARIO = rsu_imu_paper_scenario()
EPOCHS = [list(epoch) for epoch in rsu_imu_epochs(SCENARIO, np.random.default_rng(7))]


def wire(observation: Any) -> dict[str, Any]:
    if isinstance(observation, RsuObservation):
        return {
            "type": "rsu",
            "t": observation.t,
            "rsu_id": observation.rsu_id,
            "range": observation.range,
            "bearing": observation.bearing,
        }
    assert isinstance(observation, GyroObservation)
    return {"type": "gyro", "t": observation.t, "yaw_rate": observation.yaw_rate}


def batch(seq: int, first: int, count: int) -> dict[str, Any]:
    return {"seq": seq, "measurements": [wire(o) for epoch in EPOCHS[first : first + count] for o in epoch]}


@contextmanager
def receiver() -> Iterator[tuple[str, dict[str, float]]]:
    """A callback on 127.0.0.1: yields its URL and a dict address -> monotonic arrival of its first notification."""
    arrivals: dict[str, float] = {}

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = json.loads(self.rfile.read(int(self.headers.get("Content-Length", "0"))))
            arrivals.setdefault(body["address"], time.monotonic())
            self.send_response(204)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, format: str, *args: Any) -> None:
            return

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/notify", arrivals
    finally:
        server.shutdown()
        server.server_close()


def timed(client: httpx.Client, path: str, count: int, **params: Any) -> tuple[float, float]:
    """Median and largest latency (ms) of ``count`` sequential GETs."""
    latencies = []
    for _ in range(count):
        start = time.perf_counter()
        response = client.get(path, params=params, headers=ADMIN)
        latencies.append((time.perf_counter() - start) * 1000.0)
        assert response.status_code == 200, response.text
    return statistics.median(latencies), max(latencies)


def run(args: argparse.Namespace, store: str, workdir: Path) -> None:
    environment = clean_environment(
        EDGEPOS_STORE=store,
        EDGEPOS_ADMIN_KEY=ADMIN_KEY,
        EDGEPOS_ORIGIN_LAT="48.137",
        EDGEPOS_ORIGIN_LON="11.575",
        EDGEPOS_LOCATION_POLL_S=str(args.poll),
        EDGEPOS_RATE_LIMIT_PER_S="0",
        EDGEPOS_MAX_SESSIONS=str(max(10_000, args.vehicles)),
        EDGEPOS_LOG_LEVEL="warning",
    )
    with (
        running(
            serve_command(args.workers), environment, workdir / "server.log", ready_timeout_s=300.0
        ) as base,
        httpx.Client(base_url=base, timeout=60.0) as client,
    ):
        rsus = [{"id": r.id, "x": r.x, "y": r.y} for r in SCENARIO.rsus]
        assert client.put("/v1/rsus", json={"rsus": rsus}, headers=ADMIN).status_code == 200
        gate = {"circle": {"center": [90.0, 0.0], "radius": 15.0}}
        assert client.put("/v1/zones/gate", json=gate, headers=ADMIN).status_code == 200
        tokens = []
        for number in range(args.vehicles):
            created = client.post("/v1/sessions", json={"vehicle_id": f"car-{number}"}, headers=ADMIN).json()
            token = {"Authorization": f"Bearer {created['token']}"}
            answer = client.post(
                f"/v1/sessions/{created['session_id']}/batches", json=batch(1, 0, 20), headers=token
            )
            assert answer.status_code == 200, answer.text
            tokens.append((created["session_id"], token))
        every = timed(client, "/location/v3/queries/users", args.queries)
        one = timed(client, "/location/v3/queries/users", args.queries, address="acr:car-0")
        zones = timed(client, "/location/v3/queries/zones", args.queries)
        print(
            f"vehicles {args.vehicles}, store {store.split(':', 1)[0]}, workers {args.workers}, poll {args.poll} s"
        )
        print(f"GET queries/users (all)      median {every[0]:.1f} ms, max {every[1]:.1f} ms")
        print(f"GET queries/users?address=   median {one[0]:.1f} ms, max {one[1]:.1f} ms")
        print(f"GET queries/zones            median {zones[0]:.1f} ms, max {zones[1]:.1f} ms")
        with receiver() as (url, arrivals):
            body = {
                "subscriptionType": "ZoneLocationEventSubscription",
                "zoneId": "gate",
                "callbackReference": url,
            }
            created = client.post("/location/v3/subscriptions/zones", json=body, headers=ADMIN)
            assert created.status_code == 201, created.text
            cpu_before, idle_start = service_cpu_s(base), time.monotonic()
            time.sleep(args.idle)
            idle_cpu = (service_cpu_s(base) - cpu_before) / (time.monotonic() - idle_start)
            delays = []
            for number in range(min(args.crossings, args.vehicles)):
                session_id, token = tokens[number]
                answer = client.post(
                    f"/v1/sessions/{session_id}/batches", json=batch(2, 20, 130), headers=token
                )
                assert answer.status_code == 200, answer.text
                answered = time.monotonic()
                deadline = answered + 10.0 * args.poll + 10.0
                while f"acr:car-{number}" not in arrivals and time.monotonic() < deadline:
                    time.sleep(0.005)
                delays.append((arrivals[f"acr:car-{number}"] - answered) * 1000.0)
        print(
            f"zone entry -> notification   median {statistics.median(delays):.0f} ms, min {min(delays):.0f} ms, "
            f"max {max(delays):.0f} ms over {len(delays)} crossings"
        )
        print(
            f"service CPU while idle with one zone subscription over every vehicle: {idle_cpu * 100:.1f}% of a core"
        )
        print(f"cores {os.cpu_count()}, load average {os.getloadavg()[0]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vehicles", type=int, default=100)
    parser.add_argument("--poll", type=float, default=1.0)
    parser.add_argument("--crossings", type=int, default=10)
    parser.add_argument("--queries", type=int, default=20)
    parser.add_argument("--idle", type=float, default=10.0)
    parser.add_argument("--store", choices=("memory", "redis"), default="memory")
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="edgepos-location-") as directory:
        workdir = Path(directory)
        if args.store == "memory":
            if args.workers != 1:
                parser.error("--store memory serves one worker only")
            run(args, "memory", workdir)
            return
        binary = redis_binary()
        if binary is None:
            parser.error("redis-server is not installed")
        server = RedisServer(binary, workdir / "redis", "--save", "", "--appendonly", "no")
        server.start()
        try:
            run(args, server.url("bench:"), workdir)
        finally:
            server.stop()


if __name__ == "__main__":
    main()
