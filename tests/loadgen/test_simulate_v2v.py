"""``edgepos simulate --scenario v2v`` against a real server over a socket: every vehicle gets a fix
per epoch, ranges are used, and each group's RMSE matches the in-process evaluation of the same
seed and run within Monte Carlo noise (the server may answer a neighbour's request of the same step
first, so a vehicle sees its estimate of step k or k-1)."""

from __future__ import annotations

import asyncio
import math

from edgepos.eval.v2v import run_method
from edgepos.loadgen.v2v_sim import run_v2v
from edgepos.sim.v2v import VEHICLE_IDS, make_run
from loadgenhelp import ADMIN_KEY

EPOCHS = 60
#: How far the RMSE over HTTP may fall below / rise above the in-process one, as a fraction of it.
#: The in-process evaluation ranges against every neighbour's estimate of step k-1; over HTTP a
#: neighbour whose batch of step k the server happened to apply first is seen at step k, which is
#: fresher and lowers the error. Which requests go first is up to the scheduler (a busy machine
#: serialises them in random order): in-process replays of seed 3's two groups with ~150 such
#: orderings (one after another in random order, or a random mix of step k and k-1 estimates) fell
#: by up to 10.2 % and rose by at most 2.0 %; the margin below is twice that, the one above unchanged.
BELOW, ABOVE = 0.2, 0.1


def test_v2v_over_http_matches_in_process(server_url):
    vehicles, _ = asyncio.run(
        run_v2v(
            server_url, groups=2, seed=3, layout="ring", batch_epochs=1, epochs=EPOCHS, admin_key=ADMIN_KEY
        )
    )
    assert all(v.error is None and len(v.fixes) == EPOCHS for v in vehicles), [v.error for v in vehicles]
    for group in range(2):
        members = [v for v in vehicles if v.group == group]
        used = [u for v in members for f in v.fixes[2:] for u in f.measurements if u.type == "v2v_range"]
        assert used and sum(u.used for u in used) >= 0.9 * len(used), [u.reason for u in used if not u.used][
            :3
        ]
        over_http = math.sqrt(sum(v.position_rmse**2 for v in members) / len(members))
        # The draws depend on the run's length: the simulator sends the first EPOCHS of the full run.
        squared, _, _ = run_method(make_run(3, group, "ring"), "augUKF")
        in_process = math.sqrt(float(squared[1:EPOCHS].sum()) / (len(VEHICLE_IDS) * (EPOCHS - 1)))
        difference = over_http - in_process
        assert -BELOW * in_process < difference < ABOVE * in_process, (over_http, in_process)
