"""Run a ``redis-server`` on a free loopback port, in its own data directory, and restart or kill it.

Used by the Redis store's tests, the fault tests and the Redis benchmarks (never by the service
itself). Loopback only; the caller chooses persistence through ``redis-server`` options.
"""

from __future__ import annotations

import random
import shutil
import socket
import subprocess
import time
from pathlib import Path
from typing import Self

START_TIMEOUT_S = 10.0


def free_port() -> int:
    """A loopback TCP port nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def free_cluster_port(taken: set[int]) -> int:
    """A loopback port that is free together with its cluster bus port (port + 10000), both below the
    kernel's ephemeral range (so no client socket takes one meanwhile) and apart from ``taken``."""
    for _ in range(200):
        port = random.randint(10000, 22000)
        if {port, port + 10000} & {p + d for p in taken for d in (0, 10000)}:
            continue
        try:
            with (
                socket.socket(socket.AF_INET, socket.SOCK_STREAM) as one,
                socket.socket(socket.AF_INET, socket.SOCK_STREAM) as bus,
            ):
                one.bind(("127.0.0.1", port))
                bus.bind(("127.0.0.1", port + 10000))
        except OSError:
            continue
        taken.add(port)
        return port
    raise RuntimeError("no free loopback port pair for a cluster node")


def redis_binary() -> str | None:
    """The ``redis-server`` on PATH, or None."""
    return shutil.which("redis-server")


class RedisServer:
    """One redis-server on 127.0.0.1:``port`` with its data in ``directory``; restartable on the
    same port and directory (so an append-only file or snapshot is read back)."""

    def __init__(self, binary: str, directory: Path, *config: str, port: int | None = None) -> None:
        self.binary = binary
        self.directory = directory
        self.port = free_port() if port is None else port
        self.config = config
        self.process: subprocess.Popen[bytes] | None = None

    def url(self, prefix: str = "", **query: str) -> str:
        params = {"prefix": prefix, **query} if prefix else dict(query)
        tail = "&".join(f"{key}={value}" for key, value in params.items())
        return f"redis://127.0.0.1:{self.port}/0" + (f"?{tail}" if tail else "")

    def start(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        command = [
            self.binary,
            "--port", str(self.port),
            "--bind", "127.0.0.1",
            "--dir", str(self.directory),
            "--daemonize", "no",
            "--logfile", "redis.log",
            *self.config,
        ]  # fmt: skip
        self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                log = (self.directory / "redis.log").read_text(errors="replace")[-2000:]
                raise RuntimeError(f"redis-server exited with {self.process.returncode}: {log}")
            if self.command("PING") == b"+PONG\r\n":
                return
            time.sleep(0.02)
        self.stop()
        raise RuntimeError(f"redis-server did not answer on port {self.port} within {START_TIMEOUT_S} s")

    def command(self, *words: str) -> bytes:
        """Send one inline command and return the raw reply (b'' if nobody answers)."""
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=1.0) as conn:
                conn.sendall((" ".join(words) + "\r\n").encode())
                return conn.recv(65536)
        except OSError:
            return b""

    def kill(self) -> None:
        """SIGKILL: no shutdown save, no final AOF flush beyond what Redis already wrote."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        self.process = None

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
        self.process = None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def redis_cli_binary() -> str | None:
    """The ``redis-cli`` on PATH (Debian's redis-tools, installed with redis-server), or None."""
    return shutil.which("redis-cli")


class RedisClusterProcesses:
    """A Redis Cluster on loopback: ``primaries`` primaries with ``replicas`` replicas each, one
    redis-server per node in its own directory under ``directory``, joined by ``redis-cli --cluster
    create`` (which spreads the 16384 slots evenly over the primaries). For tests and benchmarks only."""

    NODE_TIMEOUT_MS = 1000
    """How long a primary may be silent before its replica takes over (``cluster-node-timeout``)."""

    def __init__(
        self, binary: str, directory: Path, *config: str, primaries: int = 3, replicas: int = 1
    ) -> None:
        cli = redis_cli_binary()
        if cli is None:
            raise RuntimeError("redis-cli is not installed (apt-get install -y redis-tools)")
        self.cli = cli
        taken: set[int] = set()
        self.nodes = [
            RedisServer(
                binary,
                directory / f"node-{index}",
                "--cluster-enabled",
                "yes",
                "--cluster-config-file",
                "nodes.conf",
                "--cluster-node-timeout",
                str(self.NODE_TIMEOUT_MS),
                "--cluster-require-full-coverage",
                "no",
                "--repl-diskless-sync-delay",  # a replica's first sync starts at once, not after 5 s
                "0",
                *config,
                port=free_cluster_port(taken),
            )
            for index in range(primaries * (1 + replicas))
        ]
        self.replicas = replicas
        self.primary_count = primaries

    def url(self, prefix: str = "") -> str:
        """``redis-cluster://`` URL naming every node as a startup node."""
        hosts = ",".join(f"127.0.0.1:{node.port}" for node in self.nodes if node.process is not None)
        return f"redis-cluster://{hosts}" + (f"?prefix={prefix}" if prefix else "")

    def start(self) -> None:
        for node in self.nodes:
            node.start()
        addresses = [f"127.0.0.1:{node.port}" for node in self.nodes]
        subprocess.run(
            [
                self.cli,
                "--cluster",
                "create",
                *addresses,
                "--cluster-replicas",
                str(self.replicas),
                "--cluster-yes",
            ],
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            timeout=60,
        )
        self.wait_until_ok()
        self.wait_until_replicated()

    def wait_until_replicated(self, timeout_s: float = 30.0) -> None:
        """Until every primary has all its replicas online (the first full sync done): before that a
        replica promoted in a failover would hold nothing."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            infos = [
                node.command("INFO", "replication").decode(errors="replace") for node in self.primaries()
            ]
            if all(info.count("state=online") >= self.replicas for info in infos):
                return
            time.sleep(0.1)
        raise RuntimeError(f"the replicas did not finish their first sync within {timeout_s} s")

    def wait_until_ok(self, timeout_s: float = 30.0, *, without: RedisServer | None = None) -> None:
        """Until every running node reports ``cluster_state:ok`` and they agree on all the primaries (with
        ``without``: a primary just killed, until a replica has been promoted in its place; a node without
        persistence restarted before that would come back as the empty primary of its slots)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            running = [node for node in self.nodes if node.process is not None]
            if all(b"cluster_state:ok" in node.command("CLUSTER", "INFO") for node in running):
                views = {tuple(sorted(self._primary_ports(node))) for node in running}
                view = next(iter(views))
                if (
                    len(views) == 1
                    and len(view) == self.primary_count
                    and (without is None or without.port not in view)
                ):
                    return
            time.sleep(0.1)
        raise RuntimeError(f"the cluster did not reach cluster_state:ok within {timeout_s} s")

    @staticmethod
    def _primary_ports(node: RedisServer) -> list[int]:
        ports = []
        for line in node.command("CLUSTER", "NODES").decode(errors="replace").splitlines():
            fields = line.split()
            if len(fields) > 8 and "master" in fields[2] and "fail" not in fields[2]:
                ports.append(int(fields[1].split("@")[0].rsplit(":", 1)[1]))
        return ports

    def node_id(self, node: RedisServer) -> str:
        return node.command("CLUSTER", "MYID").decode().split("\r\n")[1]

    def primaries(self) -> list[RedisServer]:
        """The running nodes that currently are primaries holding slots."""
        running = [node for node in self.nodes if node.process is not None]
        ports = set(self._primary_ports(running[0]))
        return [node for node in running if node.port in ports]

    def slot_owner(self, slot: int) -> RedisServer:
        for line in self.primaries()[0].command("CLUSTER", "NODES").decode().splitlines():
            fields = line.split()
            if "master" not in fields[2]:
                continue
            for span in fields[8:]:
                if span.startswith("["):
                    continue
                low, _, high = span.partition("-")
                if int(low) <= slot <= int(high or low):
                    port = int(fields[1].split("@")[0].rsplit(":", 1)[1])
                    return next(node for node in self.nodes if node.port == port)
        raise LookupError(f"no primary serves slot {slot}")

    def reshard(self, source: RedisServer, target: RedisServer, slots: int) -> None:
        """Move ``slots`` slots (with their keys, by MIGRATE) from ``source`` to ``target``, as an operator
        rebalancing the cluster would; clients follow the ASK and MOVED redirections meanwhile. redis-cli
        refuses to start while the nodes' views of the slots still differ (gossip after a create or a
        failover), so it waits for ``--cluster check`` to pass first."""
        self.wait_until_consistent(source)
        moved = subprocess.run(
            [
                self.cli,
                "--cluster",
                "reshard",
                f"127.0.0.1:{source.port}",
                "--cluster-from",
                self.node_id(source),
                "--cluster-to",
                self.node_id(target),
                "--cluster-slots",
                str(slots),
                "--cluster-yes",
            ],
            check=False,
            capture_output=True,
            timeout=120,
        )
        if moved.returncode != 0:
            said = (moved.stdout + moved.stderr).decode(errors="replace").strip().splitlines()[-5:]
            raise RuntimeError(f"redis-cli --cluster reshard failed ({moved.returncode}): {' | '.join(said)}")

    def wait_until_consistent(self, node: RedisServer, timeout_s: float = 30.0) -> None:
        """Until ``redis-cli --cluster check`` from ``node`` passes: every node agrees on the slots, none
        is open (migrating or importing) and all 16384 are covered."""
        deadline = time.monotonic() + timeout_s
        while True:
            check = subprocess.run(
                [self.cli, "--cluster", "check", f"127.0.0.1:{node.port}"],
                check=False,
                capture_output=True,
                timeout=30,
            )
            if check.returncode == 0:
                return
            if time.monotonic() > deadline:
                said = check.stdout.decode(errors="replace").strip().splitlines()[-3:]
                raise RuntimeError(
                    f"the cluster's nodes did not agree within {timeout_s} s: {' | '.join(said)}"
                )
            time.sleep(0.2)

    def stop(self) -> None:
        for node in self.nodes:
            node.stop()

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
