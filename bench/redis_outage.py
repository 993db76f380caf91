"""Fault run: Redis killed (SIGKILL) for a few seconds under ``edgepos loadtest --verify``.

Starts, on loopback, a ``redis-server`` with the chosen persistence and ``edgepos serve --workers 2``
on it, puts ``--vehicles`` vehicles (20 Hz, 10-epoch batches) on it with ``--verify``, kills Redis
``--kill-after`` s after every vehicle's first session is open, starts it again ``--outage`` s later (same port, same directory,
so it reads back what it had persisted) and prints what the load generator reports: errors by code,
and every session read back with the acknowledged batches found and lost and the window over which
the lost ones were acknowledged. One run per persistence setting:

  * ``always``: append-only file fsynced on every write (no acknowledged batch may be lost),
  * ``everysec``: the recommended production setting (a killed Redis process loses nothing the OS
    already has; up to about a second of writes is at risk only if the machine itself goes down),
  * ``none``: no persistence (the restarted Redis is empty: everything acknowledged is lost).

    python bench/redis_outage.py [--vehicles N] [--duration S] [--persistence always,everysec,none]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

from edgepos.loadgen.loadtest import LoadConfig, run_load
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command

ADMIN_KEY = "outage-admin-key-" + os.urandom(8).hex()
PERSISTENCE = {
    "always": ("--appendonly", "yes", "--appendfsync", "always", "--save", ""),
    "everysec": ("--appendonly", "yes", "--appendfsync", "everysec", "--save", ""),
    "none": ("--appendonly", "no", "--save", ""),
}


def _live_sessions(redis: RedisServer) -> int:
    reply = redis.command(
        "EVAL", "\"return #redis.call('KEYS', 'outage:session:*')\"", "0"
    )  # inline: one quoted word
    return int(reply[1:].split(b"\r\n")[0]) if reply.startswith(b":") else 0


def one_run(binary: str, persistence: str, args: argparse.Namespace, directory: Path) -> dict:
    redis = RedisServer(binary, directory / f"redis-{persistence}", *PERSISTENCE[persistence])
    redis.start()
    try:
        store = redis.url("outage:", socket_timeout="0.5", socket_connect_timeout="0.5")
        environment = clean_environment(
            EDGEPOS_STORE=store,
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_DEMO_RSUS="true",
            EDGEPOS_RATE_LIMIT_PER_S="0",
        )
        with running(
            serve_command(2), environment, directory / f"serve-{persistence}.log", ready_timeout_s=300
        ) as url:
            config = LoadConfig(
                url=url,
                vehicles=args.vehicles,
                rate=20.0,
                batch=10,
                duration=args.duration,
                admin_key=ADMIN_KEY,
                timeout=5.0,
                verify=True,
            )
            result: dict = {}
            load = threading.Thread(target=lambda: result.update(report=asyncio.run(run_load(config))))
            started = time.monotonic()
            load.start()
            while (
                _live_sessions(redis) < args.vehicles and load.is_alive()
            ):  # every vehicle's first trip open
                time.sleep(0.05)
            time.sleep(args.kill_after)
            redis.kill()
            killed = time.monotonic() - started
            time.sleep(args.outage)
            redis.start()
            load.join()
        report = result["report"].to_json()
        report["killed_at_s"], report["outage_s"] = killed, args.outage
        return report
    finally:
        redis.stop()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=100)
    parser.add_argument("--duration", type=float, default=15.0, help="seconds of load (default 15)")
    parser.add_argument(
        "--kill-after",
        type=float,
        default=5.0,
        help="seconds after every vehicle opened its session (default 5)",
    )
    parser.add_argument("--outage", type=float, default=3.0, help="seconds Redis stays down (default 3)")
    parser.add_argument("--persistence", default="always,everysec,none")
    args = parser.parse_args()
    binary = redis_binary()
    if binary is None:
        print("redis-server is not installed (make redis-server)", file=sys.stderr)
        return 2
    print(
        f"{args.vehicles} vehicles x 20 Hz, 10-epoch batches, {args.duration:g} s, 2 workers on Redis; Redis SIGKILLed "
        f"about {args.kill_after:g} s in, down {args.outage:g} s; load average {os.getloadavg()[0]:.2f}"
    )
    header = "persistence  503s  other errors  sessions  acknowledged   found   lost  loss window  gone  inconsistent"
    print(header)
    with tempfile.TemporaryDirectory(prefix="edgepos-outage-") as scratch:
        for persistence in args.persistence.split(","):
            report = one_run(binary, persistence, args, Path(scratch))
            verify, errors = report["verify"], report["errors_by_code"]
            unavailable = errors.get("unavailable", 0)
            window = "-" if verify["loss_window_s"] is None else f"{verify['loss_window_s']:.2f} s"
            print(
                f"{persistence:<11} {unavailable:>5} {sum(errors.values()) - unavailable:>13} "
                f"{verify['sessions_checked']:>9} {verify['acknowledged_batches']:>13} {verify['found']:>7} "
                f"{verify['lost']:>6} {window:>12} {verify['sessions_gone']:>5} {verify['mismatches']:>13}"
                + (f"  (unreadable {verify['unreadable']})" if verify["unreadable"] else "")
            )
            print(f"    errors by code {errors}; trips opened again {report['trips']['started']}")
            for sample in verify["samples"][:2]:
                print(f"    e.g. {sample}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
