"""Benchmark: what the cooperative integrity monitor costs per epoch of ``v2v_coop``.

Runs the V2V paper's straight scene (runs 0 .. N-1, four vehicles in lockstep as ``eval v2v`` does)
with the monitor off and on, interleaved pair by pair so that load on the machine hits both alike,
and prints the microseconds per epoch in the pipeline of each method and the ratio per pair.

    python bench/cooperative_integrity.py [--runs N] [--pairs P]
"""

from __future__ import annotations

import argparse

from edgepos.eval import v2v
from edgepos.sim import v2v as sim


def per_epoch(integrity: bool, runs: int) -> dict[str, float]:
    """Microseconds per epoch in the pipeline, per method, with the monitor on or off."""
    v2v.PAPER_OPTIONS = {**sim.PAPER_OPTIONS, "integrity": integrity}
    totals: dict[str, list[float]] = {}
    for r in range(runs):
        run = sim.make_run(0, r, "straight")
        for method in ("GPS/DR", "UKF", "augUKF"):
            _, seconds, epochs = v2v.run_method(run, method)
            entry = totals.setdefault(method, [0.0, 0.0])
            entry[0] += seconds
            entry[1] += epochs
    return {method: seconds / epochs * 1e6 for method, (seconds, epochs) in totals.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--pairs", type=int, default=2)
    args = parser.parse_args()
    for pair in range(args.pairs):
        off, on = per_epoch(False, args.runs), per_epoch(True, args.runs)
        cells = ", ".join(f"{m} {off[m]:.0f} -> {on[m]:.0f} us ({on[m] / off[m] - 1:+.0%})" for m in off)
        print(f"pair {pair + 1}: {cells}")


if __name__ == "__main__":
    main()
