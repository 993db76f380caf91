"""Benchmark: what late measurements cost the rsu_imu pipeline with its lag window, against in order.

The RSU + IMU paper scenario (20 Hz, 4 RSUs + gyro per epoch) is fed to the registered ``rsu_imu``
pipeline (lag window at its defaults, ``max_delay_s`` 1 s) as a vehicle would send it, in batches of
B epochs (each sent when its last epoch has happened): once in order, once with 30 % of the RSU
measurements 0.05-0.5 s late (``sim.delivery``: a batch holds what arrived since the previous one, so
late measurements land in later batches and the window replays from a checkpoint). The two deliveries
are timed interleaved, round after round, so that load on the machine hits both alike; each figure is
the median over rounds of CPU time per epoch of the scenario. Also printed: the session state's size
(in order and late) and how many epochs each late batch filtered again, and a check that both runs end
in the same filter state (replay is exact).

With ``--service`` the same deliveries also go over HTTP to a real ``edgepos serve`` (1 worker, the
in-process store, rate limit off) started by the script, one session per delivery and round, and the
figure is the server process tree's own CPU time (user + system, from /proc) per epoch: what an
operator's server pays for an epoch, HTTP, validation, storage and the filter together.

Target (issue 15): the cost of an epoch with 30 % late at most 3 x an in-order epoch.

    python bench/late_measurements.py [--rounds N] [--epochs K] [--batch-epochs 1,5,20] [--service] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from edgepos.core.compiled import warm_up
from edgepos.eval.rsu_imu_montecarlo import initial_state
from edgepos.pipelines import lag
from edgepos.pipelines.registry import get_pipeline
from edgepos.sim.delivery import LateDelivery, arrival_batches, arrival_times, in_order_batches
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import environment, rsu_imu_epochs

TARGET_RATIO = 3.0


def _run(pipeline, options, start, batches, env) -> tuple[float, bytes, list[int]]:
    """CPU seconds of sending ``batches`` in order through a new session, the final state, and the
    fixes per batch."""
    state = pipeline.create(options, start)
    sizes = []
    began = time.process_time()
    for batch in batches:
        fixes, state = pipeline.process(state, batch, env)
        sizes.append(len(fixes))
    return time.process_time() - began, state, sizes


def _process_tree_cpu_s(root: int) -> float:
    """User + system CPU seconds of process ``root`` and its live descendants (Linux /proc)."""
    ticks = os.sysconf("SC_CLK_TCK")
    parents: dict[int, int] = {}
    times: dict[int, float] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # the process ended while we looked
        pid = int(entry.name)
        parents[pid] = int(fields[1])
        times[pid] = (int(fields[11]) + int(fields[12])) / ticks
    tree, frontier = {root}, [root]
    while frontier:
        parent = frontier.pop()
        children = [pid for pid, ppid in parents.items() if ppid == parent and pid not in tree]
        tree.update(children)
        frontier += children
    return sum(times.get(pid, 0.0) for pid in tree)


def _service_rows(scenario, start, deliveries, rounds: int) -> dict[str, list[float]]:
    """Server CPU seconds per delivery and round: each delivery's batches sent over HTTP, one after the
    other, through a new session of a real server."""
    import tempfile

    from edgepos.loadgen import common
    from edgepos.loadgen.localserver import clean_environment, running, serve_command
    from edgepos_client import EdgeposClient

    admin = "bench-late-admin-" + os.urandom(8).hex()
    seconds: dict[str, list[float]] = {name: [] for name in deliveries}
    with tempfile.TemporaryDirectory(prefix="edgepos-bench-late-") as tmp:
        environment = clean_environment(
            EDGEPOS_ADMIN_KEY=admin,
            EDGEPOS_ADMIN_KEY_FILE=str(Path(tmp) / "admin.key"),
            EDGEPOS_LOG_LEVEL="warning",
            EDGEPOS_RATE_LIMIT_PER_S="0",  # capacity, not policy: one-epoch batches as fast as answered
        )
        with (
            running(serve_command(1), environment, Path(tmp) / "server.log", ready_timeout_s=300.0) as url,
            EdgeposClient(url, admin, timeout=60.0) as client,
        ):
            port = int(url.rsplit(":", 1)[1])
            server = _server_pid(port)
            client.put_rsus(common.scenario_rsus(scenario))
            initial = common.initial_state(scenario)
            wired = {
                name: [[common.to_wire(o) for o in b] for b in batches]
                for name, batches in deliveries.items()
            }
            for round_index in range(rounds + 1):  # round 0 warms the server up and is not counted
                for name, batches in wired.items():
                    session = client.create_session(
                        f"late-{name}-{round_index}", "rsu_imu", initial_state=initial
                    )
                    began = _process_tree_cpu_s(server)
                    for batch in batches:
                        client.send_batch(session, batch)
                    spent = _process_tree_cpu_s(server) - began
                    client.delete_session(session)
                    if round_index:
                        seconds[name].append(spent)
    return seconds


def _server_pid(port: int) -> int:
    """The pid of the ``edgepos serve`` started on ``port`` (its command line names the port)."""
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                argv = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"serve" in argv and str(port).encode() in argv:
                return int(entry.name)
    raise RuntimeError(f"no edgepos serve process found on port {port}")


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--epochs", type=int, default=400, help="epochs of the scenario per run (default 400)"
    )
    parser.add_argument("--batch-epochs", default="1,5,20", help="batch sizes to measure (default 1,5,20)")
    parser.add_argument("--fraction", type=float, default=0.3)
    parser.add_argument("--max-delay", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--service", action="store_true", help="also measure a real server's CPU per epoch over HTTP"
    )
    args = parser.parse_args()

    warm_up()
    scenario = rsu_imu_paper_scenario()
    env = environment(scenario)
    pipeline = get_pipeline("rsu_imu")
    options = pipeline.resolve_options({})
    start = initial_state(scenario)
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(args.seed))[: args.epochs]
    observations = [o for epoch in epochs for o in epoch]
    delivery = LateDelivery(args.fraction, args.max_delay)
    arrivals = arrival_times(observations, delivery, np.random.default_rng([args.seed, 1]))
    late_count = int(np.sum(arrivals > np.array([o.t for o in observations])))

    print(
        f"rsu_imu, paper scenario, {len(epochs)} epochs, {late_count} of {len(observations)} measurements late "
        f"({delivery.fraction:.0%} of RSU measurements, {delivery.min_delay_s:g}-{delivery.max_delay_s:g} s); "
        f"lag window max_delay_s {options['max_delay_s']:g} s; {args.rounds} rounds, medians; "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}, {platform.python_version()}"
    )
    header = (
        f"{'batch':>6} {'in order us/epoch':>18} {'late us/epoch':>14} {'ratio':>6} {'target':>7} "
        f"{'state in order B':>17} {'state late B':>13} {'fixes/batch late':>17} {'same end state':>15}"
    )
    print(header)
    results = []
    for batch_epochs in [int(b) for b in args.batch_epochs.split(",")]:
        ordered = in_order_batches(observations, batch_epochs)
        late = arrival_batches(observations, arrivals, batch_epochs)
        in_order_s, late_s = [], []
        for _ in range(args.rounds):
            seconds, state_in_order, _ = _run(pipeline, options, start, ordered, env)
            in_order_s.append(seconds)
            seconds, state_late, sizes = _run(pipeline, options, start, late, env)
            late_s.append(seconds)
        per_in_order = statistics.median(in_order_s) / len(epochs) * 1e6
        per_late = statistics.median(late_s) / len(epochs) * 1e6
        ratio = per_late / per_in_order
        same = lag._unpack(state_in_order).current == lag._unpack(state_late).current
        row = {
            "batch_epochs": batch_epochs,
            "in_order_us_per_epoch": per_in_order,
            "late_us_per_epoch": per_late,
            "ratio": ratio,
            "state_bytes_in_order": len(state_in_order),
            "state_bytes_late": len(state_late),
            "fixes_per_late_batch": float(np.mean(sizes)),
            "same_end_state": same,
        }
        results.append(row)
        print(
            f"{batch_epochs:>6} {per_in_order:>18.1f} {per_late:>14.1f} {ratio:>6.2f} "
            f"{'ok' if ratio <= TARGET_RATIO else 'MISSED':>7} {len(state_in_order):>17} {len(state_late):>13} "
            f"{np.mean(sizes):>17.2f} {same!s:>15}"
        )
    service_results = []
    if args.service:
        print()
        print("over HTTP, a real server (1 worker, in-process store): server CPU per epoch")
        print(f"{'batch':>6} {'in order us/epoch':>18} {'late us/epoch':>14} {'ratio':>6} {'target':>7}")
        for batch_epochs in [int(b) for b in args.batch_epochs.split(",")]:
            deliveries = {
                "in-order": in_order_batches(observations, batch_epochs),
                "late": arrival_batches(observations, arrivals, batch_epochs),
            }
            seconds = _service_rows(scenario, start, deliveries, args.rounds)
            per_in_order = statistics.median(seconds["in-order"]) / len(epochs) * 1e6
            per_late = statistics.median(seconds["late"]) / len(epochs) * 1e6
            ratio = per_late / per_in_order
            service_results.append(
                {
                    "batch_epochs": batch_epochs,
                    "in_order_us_per_epoch": per_in_order,
                    "late_us_per_epoch": per_late,
                    "ratio": ratio,
                }
            )
            print(
                f"{batch_epochs:>6} {per_in_order:>18.1f} {per_late:>14.1f} {ratio:>6.2f} "
                f"{'ok' if ratio <= TARGET_RATIO else 'MISSED':>7}"
            )
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    if args.json is not None:
        document = {"results": results, "service": service_results, "load_average": os.getloadavg()[0]}
        args.json.write_text(json.dumps(document, indent=2) + "\n")
    return 0 if all(r["same_end_state"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
