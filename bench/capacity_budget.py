"""The CPU budget an epoch at a target service ÷ floor ratio, against what every epoch costs whatever the
service does (``python bench/wrk_load.py --budget RATIO``, after its table).

When the box's cores are saturated, as under wrk with two workers, epochs/s is the cores divided by the
CPU an epoch takes across the box: server, wrk and redis-server. At ``ratio`` of the floor's epochs/s in
the same run that allows ``cores / (ratio x floor epochs/s)`` of CPU an epoch. Three parts of it are
spent on every epoch by any service that answers these requests with this filter:

* the floor's own server CPU: HTTP, parsing and validating the same request schema and writing fixes of
  the same shape with the service's own code (``floor_app.py``); the service's direct path skips
  FastAPI's routing, which the floor pays, so its share could be a few µs an epoch lower;
* wrk's CPU an epoch, in the floor's run (wrk does the same work for any server);
* the filter's compiled run of a 20-epoch batch (``run_call_cost.py``'s "call, whole run"): the
  numerical work itself, in one nogil numba call.

What is left is the budget for everything else: the pipeline's Python around the run, the session store
(the Redis client and redis-server), authentication, the replay record, the fix stream and admission.
"""

from __future__ import annotations

import statistics
from typing import Any

import run_call_cost


def _median(runs: list[dict[str, Any]], key: str) -> float:
    return statistics.median(run.get(key, 0.0) for run in runs)


def print_budget(
    ratio: float, floor: list[dict[str, Any]], services: dict[str, list[dict[str, Any]]], cores: int
) -> dict[str, float]:
    """Print the budget at ``ratio`` of the floor's epochs/s (medians of rounds) and what each service
    spends beyond the fixed parts; return the figures."""
    run = run_call_cost.measure(integrity=True, repeats=300)  # the service's default: monitor on
    epochs = run["epochs"]
    compiled = run["call, whole run"] / epochs
    pipeline = run["process"] / epochs
    floor_rate = _median(floor, "epochs_per_s")
    floor_server, floor_wrk = (
        _median(floor, "server_cpu_us_per_epoch"),
        _median(floor, "wrk_cpu_us_per_epoch"),
    )
    target = ratio * floor_rate
    budget = cores / target * 1e6
    fixed = floor_server + floor_wrk + compiled
    left = budget - fixed
    print(
        f"Budget at {ratio:g} of the floor ({target:,.0f} epochs/s on {cores} cores): {budget:.1f} us of CPU an epoch.\n"
        f"  spent on every epoch whatever the service does: the floor's server {floor_server:.1f} + wrk "
        f"{floor_wrk:.1f} + the filter's compiled run {compiled:.1f} (a {epochs:.0f}-epoch run, "
        f"{run['call, whole run']:.0f} us) = {fixed:.1f} us\n"
        f"  left for everything else: {left:.1f} us an epoch, {left * epochs:.0f} us a {epochs:.0f}-epoch batch\n"
        f"  the pipeline as it is (process {pipeline:.1f} us an epoch in place of the run alone): "
        f"{floor_server + floor_wrk + pipeline:.1f} us before anything else"
    )
    figures = {
        "budget_us": budget,
        "fixed_us": fixed,
        "left_us": left,
        "compiled_us": compiled,
        "pipeline_us": pipeline,
    }
    for name, runs in services.items():
        spent = sum(
            _median(runs, key)
            for key in ("server_cpu_us_per_epoch", "wrk_cpu_us_per_epoch", "redis_cpu_us_per_epoch")
        )
        print(
            f"  {name}: {spent:.1f} us an epoch in all, {spent - fixed:.1f} beyond the fixed parts "
            f"({(spent - fixed) / left:.1f} x what is left)"
            if left > 0
            else f"  {name}: {spent:.1f} us an epoch in all; nothing is left beyond the fixed parts"
        )
        figures[f"{name} us"] = spent
    return figures
