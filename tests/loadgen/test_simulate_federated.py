"""``edgepos simulate --scenario federated`` against a real server over a socket: each target's RMSE
matches the in-process evaluation of the same seed and runs within Monte Carlo noise."""

from __future__ import annotations

import asyncio
import math

from edgepos.eval.federated import run_method
from edgepos.loadgen.federated_sim import run_federated
from edgepos.sim.federated import make_run
from loadgenhelp import ADMIN_KEY

EPOCHS = 100


def test_federated_over_http_matches_in_process(server_url):
    targets, _ = asyncio.run(
        run_federated(server_url, vehicles=2, seed=5, batch_epochs=5, epochs=EPOCHS, admin_key=ADMIN_KEY)
    )
    assert all(t.error is None and len(t.fixes) == EPOCHS for t in targets), [t.error for t in targets]
    for target in targets:
        # The simulator truncates the full-length run (its draws depend on the length), and the
        # filters are causal: the first EPOCHS epochs of the full run are what was sent.
        squared, _ = run_method(make_run(5, target.index, "clean"), "GPS/DR/V2X")
        in_process = math.sqrt(float(squared[1:EPOCHS].mean()))
        used = [u for f in target.fixes[1:] for u in f.measurements if u.type == "v2v_range"]
        assert used and all(u.used for u in used), [u.reason for u in used if not u.used][:3]
        # Same draws, same sessions, same publishing rule: only JSON transport and batching differ.
        assert abs(target.position_rmse - in_process) < 1e-6 * in_process, (target.position_rmse, in_process)
