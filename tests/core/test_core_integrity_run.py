"""The integrity bank's steps inside a run's kernel (core.kernels_run: spawn, plan, prune on RSU codes,
core.integrity_run) against the bank's own (core.integrity_bank), on random banks."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core import integrity_bank, kernels_run
from edgepos.core.compiled import compiled_enabled
from edgepos.core.integrity import IntegrityBudget
from edgepos.core.integrity_bank import SeparationBank
from edgepos.core.integrity_run import after_run, run_monitor

pytestmark = pytest.mark.skipif(not compiled_enabled(), reason="the run's kernel is compiled only")

BUDGET = IntegrityBudget(1e-5, 1e-4, 1e-4, 1.5)
RSUS = ["a", "b", "c", "d", "e", "f"]


def random_bank(rng: np.random.Generator, ids: list[str]) -> SeparationBank:
    """A bank with sub-filters for ``ids``, covariances SPD and a little apart from the reference's."""
    count = len(ids) + 1
    root = rng.normal(size=(count, 6, 6))
    covs = root @ root.transpose(0, 2, 1) + 6.0 * np.eye(6)
    covs[1:] = covs[0] * (1.0 + rng.choice([0.001, 0.5], size=(count - 1, 1, 1)))
    return SeparationBank(["", *ids], rng.normal(size=(count, 6)), covs, 1.0)


@pytest.mark.parametrize("seed", range(20))
def test_spawn_plan_and_prune_on_codes_do_what_the_bank_does(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ids = list(rng.choice(RSUS, size=int(rng.integers(0, 5)), replace=False))
    in_use = list(rng.choice(RSUS, size=int(rng.integers(1, 5)), replace=False))
    bank = random_bank(rng, ids)
    reference = SeparationBank(list(bank.ids), bank.means.copy(), bank.covs.copy(), bank.t)
    # the rows' RSUs through a batch's stations: a gyro's (None), theirs in another order, one no row names
    stations = [None, "z", *rng.permutation(in_use).tolist()]
    row_stations = np.array([stations.index(rsu) for rsu in in_use])
    monitor, names = run_monitor(bank, stations, row_stations, BUDGET, 0.3, (0, 3))
    assert "z" not in names and len(monitor.means) == len(set(ids) | set(in_use)) + 1
    codes = monitor.rsu_codes
    assert [names[code] for code in codes.tolist()] == in_use
    kernels_run._spawn(monitor.means, monitor.covs, monitor.filters, codes)
    reference.spawn(in_use)
    work = kernels_run._plan_work(
        monitor.filters, codes, monitor.tables, monitor.thresholds, 0.3, monitor.fix_index
    )
    expected, covered = integrity_bank._plan_work(
        tuple(reference.ids), tuple(in_use), frozenset(), BUDGET, (0, 3), 0.3
    )
    np.testing.assert_array_equal(work, expected)
    assert kernels_run._covered(monitor.filters, codes) == covered
    kernels_run._prune(monitor.means, monitor.covs, monitor.filters, codes)
    reference.prune(in_use)
    after_run(bank, monitor, names)
    assert bank.ids == reference.ids
    np.testing.assert_array_equal(bank.means, reference.means)
    np.testing.assert_array_equal(bank.covs, reference.covs)


def test_the_bank_keeps_its_ids_list_when_a_run_changes_none() -> None:
    bank = random_bank(np.random.default_rng(1), ["a", "b"])
    ids = bank.ids
    monitor, names = run_monitor(bank, ["a", "b"], np.array([0, 1, 0, 1]), BUDGET, 0.3, (0, 3))
    assert monitor.means is bank.means  # nothing to spawn: the bank's own arrays, stepped in place
    after_run(bank, monitor, names)
    assert bank.ids is ids


def test_a_monitored_run_calls_the_kernel_with_the_types_the_warm_up_compiles(monkeypatch) -> None:
    """A type the warm-up does not give (a read-only table, an int32 code) would compile (or load) a
    second signature in every worker at its first monitored batch."""
    import numba
    from edgepos.core.compiled import warm_up
    from edgepos.pipelines.base import InitialState
    from edgepos.pipelines.registry import get_pipeline
    from edgepos.sim.scenarios import rsu_imu_paper_scenario
    from edgepos.sim.sensors import environment, rsu_imu_epochs

    calls: list[tuple] = []
    kernel = kernels_run.run_epochs

    def recorded(*args):
        calls.append(tuple(numba.typeof(a) for a in args))
        return kernel(*args)

    monkeypatch.setattr(kernels_run, "run_epochs", recorded)
    warm_up()  # its run of epochs comes first
    assert len(calls) == 1
    scenario = rsu_imu_paper_scenario()
    pipeline = get_pipeline("rsu_imu")
    x0 = scenario.initial_state
    state = pipeline.create(pipeline.resolve_options({}), InitialState(x0[0], x0[3], x0[1], x0[4]))
    epochs = rsu_imu_epochs(scenario, np.random.default_rng(5))
    for first in range(0, 100, 20):
        _, state = pipeline.process(
            state, [o for e in epochs[first : first + 20] for o in e], environment(scenario)
        )
    assert len(calls) > 2
    assert set(calls[1:]) == {calls[0]}
