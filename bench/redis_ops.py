"""Benchmark: Redis commands and Redis CPU per batch, per pipeline (the capacity model's inputs).

Starts ``redis-server`` on loopback (append-only file, ``appendfsync everysec``) and ``edgepos serve``
(one worker) on it, watches Redis with ``MONITOR`` (counting the commands clients send: a Lua
script's own calls appear there marked ``lua`` and are not counted) and drives the service with
``edgepos simulate`` for each scenario: ``rsu-imu`` (the ``rsu_imu`` pipeline), ``v2v`` (four
``v2v_coop`` vehicles ranging each other, their tracks published and read through Redis) and
``federated`` (``v2x_federated``). Prints per scenario the batches, the commands per batch by name,
and Redis's CPU per batch (``INFO cpu`` before and after; MONITOR itself costs Redis some CPU, so
so that pass runs without it), the batches per second one Redis core would serve at that cost, and
the largest session hash seen (state, stored answer for replay, ``MEMORY USAGE``).

    python bench/redis_ops.py [--epochs 400] [--batch-epochs 20] [--vehicles 4]
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
from collections import Counter
from pathlib import Path

import httpx
import redis
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, running, serve_command, service_cpu_s

ADMIN_KEY = "ops-bench-admin-" + os.urandom(8).hex()
SCENARIOS = ("rsu-imu", "v2v", "federated")
_SAMPLER_COMMANDS = {"SCAN", "HSTRLEN", "MEMORY"}  # SessionSizes's; the service never sends them
_COMMAND = re.compile(rb'^\+\d+\.\d+ \[\d+ [^\]]+\] "([A-Za-z]+)"')


class Monitor:
    """Counts the commands clients send to a Redis server (MONITOR, on its own connection)."""

    def __init__(self, port: int) -> None:
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._socket = socket.create_connection(("127.0.0.1", port))
        self._socket.sendall(b"MONITOR\r\n")
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        buffer = b""
        while True:
            try:
                chunk = self._socket.recv(1 << 16)
            except OSError:
                return
            if not chunk:
                return
            buffer += chunk
            *lines, buffer = buffer.split(b"\r\n")
            for line in lines:
                found = _COMMAND.match(line)
                name = found.group(1).decode().upper() if found else ""
                # a script's own calls are not client commands; the size sampler's are not the service's
                if found and b" lua]" not in line and name not in _SAMPLER_COMMANDS:
                    with self._lock:
                        self.counts[name] += 1

    def take(self) -> Counter[str]:
        with self._lock:
            counts, self.counts = self.counts, Counter()
        return counts

    def close(self) -> None:
        self._socket.close()


class SessionSizes:
    """Samples the sessions' sizes in Redis while a scenario runs: the state, the stored answer for
    replay (``last_response``) and the whole hash (``MEMORY USAGE``), the largest seen of each."""

    def __init__(self, port: int) -> None:
        self.largest: dict[str, int] = {"state": 0, "last_response": 0, "memory": 0}
        self._client = redis.Redis(host="127.0.0.1", port=port)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(0.1):
            for key in self._client.scan_iter(match="ops:session:*", count=100):
                sizes = {
                    "state": self._client.hstrlen(key, "state"),
                    "last_response": self._client.hstrlen(key, "last_response"),
                    "memory": self._client.memory_usage(key) or 0,
                }
                for name, size in sizes.items():
                    self.largest[name] = max(self.largest[name], int(size))

    def stop(self) -> dict[str, int]:
        self._stop.set()
        self._thread.join()
        self._client.close()
        return self.largest


def _cpu(client: redis.Redis) -> float:
    info = client.info("cpu")
    return float(info["used_cpu_sys"]) + float(info["used_cpu_user"])


def _command_us(client: redis.Redis) -> dict[str, float]:
    """Microseconds spent inside each command since the last CONFIG RESETSTAT (INFO commandstats)."""
    stats = client.info("commandstats")
    return {
        name.removeprefix("cmdstat_").upper(): float(values["usec"])
        for name, values in stats.items()
        if name.startswith("cmdstat_") and name.removeprefix("cmdstat_").upper() not in {"INFO", "CONFIG"}
    }


def _batches(url: str) -> float:
    """Applied batches so far, from the service's metrics."""
    text = httpx.get(f"{url}/metrics", headers={"Authorization": f"Bearer {ADMIN_KEY}"}).text
    return sum(
        float(line.rsplit(" ", 1)[1])
        for line in text.splitlines()
        if line.startswith("edgepos_batches_total") and 'outcome="applied"' in line
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=400, help="epochs of each scenario per vehicle")
    parser.add_argument("--batch-epochs", type=int, default=20)
    parser.add_argument("--vehicles", type=int, default=4, help="vehicles (v2v: groups of four)")
    parser.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated (default all)")
    args = parser.parse_args()
    binary = redis_binary()
    if binary is None:
        print("redis-server is not installed (apt-get install -y redis-server)", file=sys.stderr)
        return 2
    print(
        f"Redis commands per batch: {args.vehicles} vehicles x {args.epochs} epochs in {args.batch_epochs}-epoch "
        f"batches per scenario, 1 worker, Redis AOF everysec; load average {os.getloadavg()[0]:.2f}",
        flush=True,
    )
    with tempfile.TemporaryDirectory(prefix="edgepos-ops-") as tmp:
        workdir = Path(tmp)
        config = ("--save", "", "--appendonly", "yes", "--appendfsync", "everysec")
        with RedisServer(binary, workdir / "redis", *config) as server:
            environment = clean_environment(
                EDGEPOS_ADMIN_KEY=ADMIN_KEY,
                EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
                EDGEPOS_LOG_LEVEL="warning",
                EDGEPOS_STORE=server.url("ops:"),
            )
            client = redis.Redis(host="127.0.0.1", port=server.port)
            with running(serve_command(1), environment, workdir / "server.log") as url:
                for scenario in args.scenarios.split(","):
                    # the federated scenario's epochs cost more: its batches are kept within the CPU budget
                    epochs_per_batch = (
                        args.batch_epochs if scenario != "federated" else args.batch_epochs // 2
                    )
                    command = [
                        sys.executable, "-m", "edgepos.cli", "simulate", "--url", url, "--scenario", scenario,
                        "--vehicles", str(args.vehicles if scenario != "v2v" else max(1, args.vehicles // 4)),
                        "--epochs", str(args.epochs), "--batch-epochs", str(epochs_per_batch),
                        "--admin-key", ADMIN_KEY, "--fast",
                    ]  # fmt: skip
                    # first with MONITOR, counting commands; then again without it, for Redis's CPU (MONITOR
                    # formatting every command's arguments for its client would dominate it)
                    monitor, sizes = Monitor(server.port), SessionSizes(server.port)
                    before_batches = _batches(url)
                    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
                    counts = monitor.take()
                    monitor.close()
                    largest = sizes.stop()
                    batches = _batches(url) - before_batches
                    client.config_resetstat()
                    before_batches, before_cpu, before_service = (
                        _batches(url),
                        _cpu(client),
                        service_cpu_s(url),
                    )
                    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
                    cpu_batches = _batches(url) - before_batches
                    cpu_us = (_cpu(client) - before_cpu) * 1e6
                    service_us = (service_cpu_s(url) - before_service) * 1e6
                    command_us = _command_us(client)
                    total = sum(counts.values())
                    per_batch = ", ".join(
                        f"{name} {count / batches:.2f}" for name, count in counts.most_common(6)
                    )
                    print(
                        f"{scenario:10s} {batches:5.0f} batches of {epochs_per_batch} epochs  {total / batches:5.2f} "
                        f"commands per batch (opening and closing the sessions included: {per_batch})  Redis CPU "
                        f"{cpu_us / cpu_batches:.0f} us per batch, {cpu_batches / cpu_us * 1e6:,.0f} batches/s per "
                        "Redis core",
                        flush=True,
                    )
                    print(
                        f"{scenario:10s} largest session: state {largest['state']:,} B, stored answer "
                        f"{largest['last_response']:,} B, the hash in Redis {largest['memory']:,} B; service CPU "
                        f"{service_us / cpu_batches:.0f} us per batch",
                        flush=True,
                    )
                    inside = ", ".join(
                        f"{name} {spent / cpu_batches:.0f}"
                        for name, spent in sorted(command_us.items(), key=lambda item: -item[1])[:8]
                    )
                    print(
                        f"{scenario:10s} Redis CPU inside commands, us per batch (INFO commandstats, a script's "
                        f"own calls within its EVALSHA): {inside}; the rest of the CPU is network I/O, "
                        "parsing and the append-only file",
                        flush=True,
                    )
            client.close()
    print(f"load average {os.getloadavg()[0]:.2f} after")
    return 0


if __name__ == "__main__":
    sys.exit(main())
