"""The test suite, N times in a row, with every CPU core kept busy.

Why: a test that leans on thread scheduling or on a quiet machine (a fixed sleep used as
synchronisation, a wall-clock deadline, two threads assumed to stay in step) passes on a developer's
idle laptop and fails at random on a loaded CI runner, where it blocks landings that have nothing to do
with it. ``test_two_vehicles_ranging_to_each_other_update_concurrently`` did exactly that: it failed in
4 of 8 runs when the CPU was busy. The bar is that ``make test`` passes 10 times in a row with every
core busy; this script is that check (``make test-under-load``).

It starts one pure-Python busy loop per core (``multiprocessing``; each one also stops by itself
after ``--spin-limit`` seconds or when this script goes away, so a killed run leaves nothing
spinning), then runs the test command ``--runs`` times, all of them, with ``CI=true`` in the
environment (what ``.ci/run`` sets), and prints for each run its exit status, passed/failed counts
(from pytest's last line) and duration, and at the end how many runs passed and failed. The busy loops
are stopped at the end, on Ctrl-C and on any error. The exit status is 1 when any run failed.

    python bench/suite_under_load.py [--runs 10] [--busy N] [--command "python -m pytest -q tests/api"]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Self

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_COMMAND = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
#: Seconds a test run may take before it is stopped and counted as failed.
RUN_TIMEOUT_S = 1800.0
#: Seconds a stopped test run gets to tear down (pytest runs fixture teardown on SIGINT) before SIGKILL.
STOP_GRACE_S = 30.0
#: Lines of a failed run's output shown with --quiet (pytest's -ra summary names the failed tests).
TAIL_LINES = 40
#: The pytest summary: "1 failed, 510 passed, 3 skipped, 2 warnings in 183.20s (0:03:03)".
SUMMARY = re.compile(r"(\d+) (passed|failed|errors?|skipped|xfailed|xpassed|deselected|warnings?)\b")


def spin(deadline: float, parent: int) -> None:
    """Burn one core in pure Python until ``deadline`` (time.monotonic()) or until ``parent`` is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it stops us
    count = 0
    while True:
        count += 1
        if count & 0xFFFFF == 0 and (time.monotonic() >= deadline or os.getppid() != parent):
            return


class BusyCores:
    """``count`` busy-loop processes while the context is open; all of them stopped on the way out."""

    def __init__(self, count: int, limit_s: float) -> None:
        self.count = count
        self.limit_s = limit_s
        self.processes: list[multiprocessing.Process] = []

    def __enter__(self) -> Self:
        deadline = time.monotonic() + self.limit_s  # CLOCK_MONOTONIC is system-wide on Linux
        try:
            for index in range(self.count):
                process = multiprocessing.Process(
                    target=spin, args=(deadline, os.getpid()), name=f"busy-{index}", daemon=True
                )
                process.start()
                self.processes.append(process)
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def alive(self) -> int:
        return sum(process.is_alive() for process in self.processes)

    def stop(self) -> None:
        for process in self.processes:
            if process.is_alive():
                process.terminate()
        for process in self.processes:
            process.join(5.0)
            if process.is_alive():
                process.kill()
                process.join()


@dataclass
class Run:
    number: int
    exit_code: int | None  # None: stopped after the run timeout
    counts: dict[str, int]
    seconds: float
    summary: str
    tail: list[str]  # the output's last lines
    named: list[str]  # pytest's FAILED / ERROR lines, wherever they were

    @property
    def ok(self) -> bool:
        return self.exit_code == 0

    def line(self, runs: int) -> str:
        failed = self.counts.get("failed", 0) + self.counts.get("error", 0)
        shown = ("passed", "failed", "error")
        extra = ", ".join(f"{n} {k}" for k, n in self.counts.items() if k not in shown)
        status = "timed out" if self.exit_code is None else f"exit {self.exit_code}"
        verdict = "ok  " if self.ok else "FAIL"
        passed = self.counts.get("passed", 0)
        text = f"{verdict} run {self.number}/{runs}: {status}, {passed} passed, {failed} failed"
        if extra:
            text += f" ({extra})"
        text += f", {self.seconds:.1f} s"
        if not self.counts and self.summary:
            text += f"  [{self.summary}]"
        return text


def parse_counts(lines: list[str]) -> tuple[dict[str, int], str]:
    """pytest's counts from its last summary line (the last line that has any); ({}, '') if none."""
    for line in reversed(lines):
        found = SUMMARY.findall(line)
        if found and (" in " in line or "no tests ran" in line):
            counts: dict[str, int] = {}
            for number, word in found:
                key = {"errors": "error", "warnings": "warning"}.get(word, word)
                counts[key] = counts.get(key, 0) + int(number)
            return counts, line.strip(" =")
    for line in reversed(lines):
        if line.strip():
            return {}, line.strip()
    return {}, ""


def stop_process_group(process: subprocess.Popen[str]) -> None:
    """SIGINT to the run's process group (pytest tears its fixtures down), SIGKILL if it lingers."""
    if process.poll() is not None:
        return
    for sig, wait_s in ((signal.SIGINT, STOP_GRACE_S), (signal.SIGKILL, 10.0)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


def run_once(number: int, command: list[str], cwd: Path, timeout_s: float, echo: bool) -> Run:
    environment = {**os.environ, "CI": "true"}
    started = time.monotonic()
    tail: deque[str] = deque(maxlen=TAIL_LINES)
    named: list[str] = []
    process = subprocess.Popen(
        command,
        cwd=cwd,
        env=environment,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        errors="replace",
        start_new_session=True,  # its own process group: stopped as a whole, never left running
    )
    timed_out = False
    try:
        assert process.stdout is not None
        # Read on this thread; a watchdog timer stops a run that exceeds its time.
        watchdog = _Watchdog(process, timeout_s)
        watchdog.start()
        try:
            for line in process.stdout:
                tail.append(line.rstrip("\n"))
                if line.startswith(("FAILED ", "ERROR ")):
                    named.append(line.rstrip("\n"))
                if echo:
                    print(line, end="", flush=True)
            process.wait()
        finally:
            timed_out = watchdog.cancel()
    finally:
        stop_process_group(process)  # on Ctrl-C or any error while it ran
    counts, summary = parse_counts(list(tail))
    exit_code = None if timed_out else process.returncode
    return Run(number, exit_code, counts, time.monotonic() - started, summary, list(tail), named)


class _Watchdog:
    """Stops ``process`` (and its group) once ``timeout_s`` have passed; ``cancel`` says whether it did."""

    def __init__(self, process: subprocess.Popen[str], timeout_s: float) -> None:
        self.process = process
        self.fired = False
        self.timer = threading.Timer(timeout_s, self._fire)
        self.timer.daemon = True

    def start(self) -> None:
        self.timer.start()

    def _fire(self) -> None:
        self.fired = True
        stop_process_group(self.process)

    def cancel(self) -> bool:
        self.timer.cancel()
        return self.fired


def _raise_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)  # unwinds through the finally blocks that stop everything


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=10, help="how many times to run the command (default 10)")
    parser.add_argument(
        "--command",
        help="the test command, split as a shell would (default: python -m pytest -q -p no:cacheprovider)",
    )
    parser.add_argument(
        "--cwd", type=Path, default=ROOT, help="where to run the command (default: the repository root)"
    )
    parser.add_argument(
        "--busy", type=int, default=os.cpu_count() or 1, help="busy-loop processes (default: one per core)"
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=RUN_TIMEOUT_S,
        help=f"seconds per run before it is stopped and counted as failed (default {RUN_TIMEOUT_S:g})",
    )
    parser.add_argument(
        "--spin-limit",
        type=float,
        help="seconds after which the busy loops stop by themselves (default: runs x timeout + 60)",
    )
    parser.add_argument(
        "--quiet", action="store_true", help="only the per-run lines (and the end of a failed run's output)"
    )
    args = parser.parse_args(argv)
    if args.runs < 1 or args.busy < 0 or not args.timeout > 0:
        parser.error("--runs must be >= 1, --busy >= 0 and --timeout > 0")
    command = shlex.split(args.command) if args.command else DEFAULT_COMMAND
    spin_limit = args.spin_limit if args.spin_limit is not None else args.runs * args.timeout + 60.0
    signal.signal(signal.SIGTERM, _raise_on_sigterm)

    print(
        f"{args.busy} busy-loop process(es) on {os.cpu_count()} core(s); "
        f"{args.runs} run(s) of: CI=true {shlex.join(command)}",
        flush=True,
    )
    results: list[Run] = []
    try:
        with BusyCores(args.busy, spin_limit) as busy:
            for number in range(1, args.runs + 1):
                if busy.alive() < args.busy:
                    print(f"warning: only {busy.alive()} of {args.busy} busy loops still running", flush=True)
                result = run_once(number, command, args.cwd, args.timeout, echo=not args.quiet)
                results.append(result)
                if args.quiet and not result.ok:
                    shown = result.tail + [line for line in result.named if line not in result.tail]
                    print("\n".join(f"    | {line}" for line in shown), flush=True)
                print(result.line(args.runs), flush=True)
    except KeyboardInterrupt:
        print(f"\ninterrupted after {len(results)} of {args.runs} run(s); busy loops stopped", flush=True)
        return 130
    passed = sum(r.ok for r in results)
    print(f"\n{'=' * 60}")
    for result in results:
        print(result.line(args.runs))
        for line in result.named:
            print(f"    {line}")
    print(f"{passed} passed, {len(results) - passed} failed ({args.runs} run(s), {args.busy} busy loop(s))")
    return 0 if passed == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
