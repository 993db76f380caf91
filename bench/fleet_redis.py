"""Benchmark: a fleet of 1,000 vehicles against two workers on Redis, from a separate process.

Starts ``redis-server`` on a free loopback port (append-only file on, ``appendfsync everysec``) and
``edgepos serve --workers 2`` on it, then runs ``edgepos loadtest`` as its own process: 1,000
vehicles at 10 Hz batched at 2 Hz (5-epoch batches, 2,000 requests/s offered) for 60 s, with
``--verify``: every session is read back at the end and its seq, batch and epoch counts must equal
what the load generator had acknowledged. Prints the load test's report (throughput, latency
percentiles, errors, lateness, verification) and the machine's load. The load generator shares the
machine's cores with the server; on a 2-core machine the offered load exceeds what the server can
answer on time, and the report says how far behind the vehicles fell.

    python bench/fleet_redis.py [--vehicles N] [--rate HZ] [--batch B] [--duration S] [--json FILE]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command

ADMIN_KEY = "fleet-admin-key-" + os.urandom(8).hex()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=1000)
    parser.add_argument("--rate", type=float, default=10.0, help="epochs per second per vehicle (default 10)")
    parser.add_argument("--batch", type=int, default=5, help="epochs per batch (default 5: 2 batches/s)")
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None, help="the load test's JSON report")
    args = parser.parse_args()
    binary = redis_binary()
    if binary is None:
        print("redis-server is not installed (apt-get install -y redis-server)", file=sys.stderr)
        return 2
    load_before = os.getloadavg()
    began = time.perf_counter()
    print(
        f"fleet benchmark: {args.vehicles} vehicles x {args.rate:g} Hz in {args.batch}-epoch batches for "
        f"{args.duration:g} s, {args.workers} workers on Redis (AOF everysec); {os.cpu_count()} cores, "
        f"load average {load_before[0]:.2f}",
        flush=True,
    )
    with tempfile.TemporaryDirectory(prefix="edgepos-fleet-") as tmp:
        workdir = Path(tmp)
        environment = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
            EDGEPOS_LOG_LEVEL="warning",
            EDGEPOS_MAX_SESSIONS=str(max(10_000, 2 * args.vehicles)),
        )
        redis_config = ("--save", "", "--appendonly", "yes", "--appendfsync", "everysec")
        with RedisServer(binary, workdir / "redis", *redis_config) as redis:
            environment["EDGEPOS_STORE"] = redis.url("fleet:")
            with running(serve_command(args.workers), environment, workdir / "server.log") as url:
                command = [
                    sys.executable,
                    "-m",
                    "edgepos.cli",
                    "loadtest",
                    "--url",
                    url,
                    "--vehicles",
                    str(args.vehicles),
                    "--rate",
                    str(args.rate),
                    "--batch",
                    str(args.batch),
                    "--duration",
                    str(args.duration),
                    "--admin-key",
                    ADMIN_KEY,
                    "--timeout",
                    "60",
                    "--verify",
                ]
                if args.json is not None:
                    command += ["--json", str(args.json)]
                status = subprocess.run(
                    command, env={**os.environ, "EDGEPOS_ADMIN_KEY": ADMIN_KEY}, check=False
                ).returncode
    print(
        f"load generator exit status {status}; load average {os.getloadavg()[0]:.2f} after; "
        f"whole benchmark {time.perf_counter() - began:.0f} s"
    )
    return status


if __name__ == "__main__":
    sys.exit(main())
