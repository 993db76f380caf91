"""Profile: where a worker's time goes while it serves batches, by layer.

Starts ``edgepos serve`` (1 worker) on the in-process store or on a ``redis-server`` it starts on
loopback (append-only file on, ``appendfsync everysec``), puts a closed loop of 20 vehicles sending
20-epoch batches on it from a separate ``edgepos loadtest`` process, and samples the worker's
Python stacks with py-spy (``pip install py-spy``; not a dependency of the project) for
``--seconds``. Each sample is charged to the innermost frame that belongs to a known layer (the
filter pipeline, the Redis client, pydantic validation, FastAPI/Starlette routing, the session
service, the middleware, fix serialisation, uvicorn's HTTP protocol), and the shares are printed.
Samples of the idle filter thread are left out; the event loop waiting inside uvloop's C code shows
as "event loop in C" (socket I/O and idle time cannot be told apart from Python stacks).

With ``--gil`` only the thread holding the GIL is sampled. One worker runs its event loop and its
filter thread under one GIL, and under saturating load it holds the GIL nearly all the time, so these
shares are those of the worker's CPU, the figure that bounds its throughput; the samples' total over
the most it could be (seconds x 200) is printed as the GIL's busy share.

py-spy samples by the wall clock, and lines that make a system call get far more samples than the CPU
they use: uvicorn's socket writes 11-16 % of the samples and the scheduler's second ``time.thread_time()``
19-24 % (a 0.56 us call), while ``perf record`` on a worker under the same load puts 3.7-4.4 % of its CPU
in the kernel altogether (docs/benchmarks.md, "svcwrite: the worker's CPU outside the filter, round
two"). Check a system call's share with perf or a thread-CPU A/B before chasing it.

    python bench/profile_service.py [--store memory|redis] [--seconds S] [--raw FILE] [--gil]
"""

from __future__ import annotations

import argparse
import collections
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
from edgepos.loadgen.localredis import RedisServer, redis_binary
from edgepos.loadgen.localserver import clean_environment, free_port

ADMIN_KEY = "profile-admin-key-" + os.urandom(8).hex()

#: Layers, in the order a frame is tested against them (first match wins for that frame).
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Redis store client (redis-py, Lua scripts)", ("edgepos/store/redis.py", "redis/")),
    ("in-process store", ("edgepos/store/memory.py",)),
    ("request validation (pydantic)", ("pydantic", "edgepos/api/schemas.py")),
    ("fix serialisation (convert, JSON)", ("edgepos/api/convert.py", "model_dump_json", "json/")),
    (
        "session service (auth, hashing, replay, bookkeeping)",
        ("edgepos/api/session_service.py", "edgepos/api/auth.py", "hashlib", "hmac"),
    ),
    (
        "logging and metrics",
        ("logging/", "prometheus_client", "edgepos/api/logs.py", "edgepos/api/metrics.py"),
    ),
    ("middleware (request id, admission, body limit)", ("edgepos/api/middleware.py",)),
    ("scheduler (the vehicles' turns, the filter lane around the pipeline)", ("edgepos/api/scheduler.py",)),
    ("FastAPI/Starlette routing and dependencies", ("starlette", "fastapi", "edgepos/api/routes")),
    ("HTTP protocol (uvicorn, httptools)", ("uvicorn", "httptools", "h11")),
)
PIPELINE = "filter pipeline (its own thread)"
LOOP_IN_C = "event loop in C (uvloop: socket I/O and idle wait)"
PLUMBING = "asyncio plumbing"


def layer_of(frame: str) -> str | None:
    for name, keys in LAYERS:
        if any(key in frame for key in keys):
            return name
    return None


def shares(raw: Path) -> tuple[collections.Counter[str], int]:
    """Samples per layer from py-spy's raw (collapsed-stack) output, and their total."""
    counts: collections.Counter[str] = collections.Counter()
    total = 0
    for line in raw.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        samples, frames = int(count), stack.split(";")
        if "Pipeline.process" in stack:
            counts[PIPELINE] += samples
        elif "_ThreadLane._serve" in stack and frames[-1].startswith("Condition.wait "):
            continue  # the filter thread waiting for work
        elif frames[-1].startswith(("Runner.run ", "select ")):
            counts[LOOP_IN_C] += samples
        else:
            counts[next((layer for layer in map(layer_of, reversed(frames)) if layer), PLUMBING)] += samples
        total += samples
    return counts, total


def wait_ready(url: str, process: subprocess.Popen[bytes], timeout_s: float = 90.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"the server exited with status {process.returncode}")
        try:
            if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise RuntimeError("the server did not become ready")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", choices=("memory", "redis"), default="redis")
    parser.add_argument("--seconds", type=float, default=12.0, help="sampling time (default 12)")
    parser.add_argument("--raw", type=Path, default=None, help="keep py-spy's raw stacks in FILE")
    parser.add_argument(
        "--gil",
        action="store_true",
        help="sample only the thread holding the GIL: the shares of the worker's Python CPU (one worker runs "
        "its event loop and its filter thread under one GIL, so this is what bounds its throughput)",
    )
    args = parser.parse_args()
    py_spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(py_spy).exists():
        print("py-spy is not installed: pip install py-spy", file=sys.stderr)
        return 2
    if args.store == "redis" and redis_binary() is None:
        print("redis-server is not installed (apt-get install -y redis-server)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="edgepos-profile-") as tmp:
        workdir = Path(tmp)
        raw = args.raw or workdir / "stacks.txt"
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        environment = clean_environment(
            EDGEPOS_ADMIN_KEY=ADMIN_KEY,
            EDGEPOS_ADMIN_KEY_FILE=str(workdir / "admin.key"),
            EDGEPOS_LOG_LEVEL="warning",
            EDGEPOS_RATE_LIMIT_PER_S="0",
        )
        redis = None
        if args.store == "redis":
            redis = RedisServer(
                redis_binary(),
                workdir / "redis",
                "--save",
                "",
                "--appendonly",
                "yes",
                "--appendfsync",
                "everysec",
            )
            redis.start()
            environment["EDGEPOS_STORE"] = redis.url("profile:")
        command = [
            sys.executable,
            "-m",
            "edgepos.cli",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
        ]
        with open(workdir / "server.log", "wb") as log:
            server = subprocess.Popen(command, env=environment, stdout=log, stderr=subprocess.STDOUT)
        try:
            wait_ready(url, server)
            duration = args.seconds + 8.0
            load = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "edgepos.cli",
                    "loadtest",
                    "--url",
                    url,
                    "--vehicles",
                    "20",
                    "--rate",
                    "20",
                    "--batch",
                    "20",
                    "--duration",
                    str(duration),
                    "--saturate",
                    "--admin-key",
                    ADMIN_KEY,
                ],
                env={**os.environ, "EDGEPOS_ADMIN_KEY": ADMIN_KEY},
                stdout=subprocess.PIPE,
                text=True,
            )
            time.sleep(4.0)  # sessions opened, the loop at full speed
            subprocess.run(
                [
                    py_spy,
                    "record",
                    "-p",
                    str(server.pid),
                    "-d",
                    str(int(args.seconds)),
                    "-r",
                    "200",
                    "-f",
                    "raw",
                    "-o",
                    str(raw),
                    "--nonblocking",
                    *(["--gil"] if args.gil else []),
                ],
                check=True,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            report, _ = load.communicate(timeout=duration + 60.0)
        finally:
            server.terminate()
            server.wait(timeout=30)
            if redis is not None:
                redis.stop()
        counts, total = shares(raw)
    print(
        f"profile of 1 worker on the {args.store} store, closed loop of 20 vehicles x 20-epoch batches, "
        f"{args.seconds:g} s at 200 Hz{', GIL holder only' if args.gil else ''}, {os.cpu_count()} cores, "
        f"load average {os.getloadavg()[0]:.2f}"
    )
    print("\n".join(line for line in report.splitlines()[1:5]))
    for name, samples in counts.most_common():
        print(f"  {100.0 * samples / total:5.1f} %  {name}")
    if args.gil:
        busy = total / (200.0 * args.seconds)
        print(f"  ({total} samples: the GIL held {100.0 * busy:.0f} % of the time)")
    else:
        print(f"  ({total} samples)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
