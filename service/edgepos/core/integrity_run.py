"""The integrity bank (``core.integrity_bank``) stepped in a run of epochs (``core.kernels_run``): the
bank's arrays as the run's kernel takes them, and the bank brought up to date from them after the run.

In the kernel an RSU is a small integer code: 0 the reference, ``k`` the RSU of the bank's sub-filter
``k`` as the run starts, then one code per RSU the run measures that has no sub-filter yet. The kernel
spawns, prunes and re-plans with codes (as ``SeparationBank.epoch`` does with ids), so a run goes on
where an RSU comes into use, the RSUs change order, or a sub-filter is dropped.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import cast

import numpy as np

from edgepos.core.compiled_run import RunMonitor
from edgepos.core.integrity import IntegrityBudget
from edgepos.core.integrity_bank import DIM, SeparationBank, budget_tables


@functools.lru_cache(maxsize=64)
def stacked_tables(budget: IntegrityBudget, filters: int) -> tuple[np.ndarray, np.ndarray]:
    """``budget_tables`` of a bank of 0, 1, .. ``filters - 1`` sub-filters, stacked (read only): the
    radial factor tables ``[h]`` and test thresholds ``[h]`` of ``h`` sub-filters."""
    pairs = [budget_tables(budget, hypotheses) for hypotheses in range(filters)]
    tables = np.stack([tables for tables, _ in pairs])
    thresholds = np.array([threshold for _, threshold in pairs])
    tables.flags.writeable = thresholds.flags.writeable = False
    return tables, thresholds


@functools.lru_cache(maxsize=16)
def fix_index(position: tuple[int, int]) -> np.ndarray:
    """Where x and y are in the fused mean, as a run's kernel reads them (read only: the cache shares it)."""
    index = np.array(position, dtype=np.int64)
    index.flags.writeable = False
    return index


def run_monitor(
    bank: SeparationBank,
    station_ids: Sequence[str | None],
    row_stations: np.ndarray,
    budget: IntegrityBudget,
    jerk_density: float,
    position: tuple[int, int],
) -> tuple[RunMonitor, list[str]]:
    """The run's monitor for ``bank`` and the run's measurement rows, row ``i`` measuring the RSU
    ``station_ids[row_stations[i]]`` (a batch's stations: a handful, where the rows are many; an RSU may
    have several, and the ids of stations no row names are not read); and the id of each code. The
    bank's own arrays are stepped in place when the run can spawn nothing, else copies with room for
    what it may spawn (:func:`after_run` takes them over). A new RSU's code follows the stations' order,
    not the rows': the kernel spawns in the rows' order whatever the codes, which only name the RSUs."""
    codes = {rsu: k for k, rsu in enumerate(bank.ids)}  # "" (the reference) is 0
    names = list(bank.ids)
    named = np.zeros(len(station_ids), dtype=np.int64)
    named[row_stations] = 1  # the stations some row names
    station_codes = named.tolist()
    for station, in_rows in enumerate(station_codes):
        if in_rows:
            rsu = cast(str, station_ids[station])  # a station a row names is an RSU's
            code = codes.get(rsu)
            if code is None:
                code = codes[rsu] = len(names)
                names.append(rsu)
            station_codes[station] = code
    rows = np.array(station_codes, dtype=np.int64).take(row_stations)
    count, capacity = len(bank.ids), len(names)
    filters = np.arange(-1, capacity, dtype=np.int64)  # codes 0 .. count - 1 in use, the rest room
    filters[0] = count
    if capacity == count:
        means, covs = bank.means, bank.covs
    else:
        means, covs = np.empty((capacity, DIM)), np.empty((capacity, DIM, DIM))
        means[:count], covs[:count] = bank.means, bank.covs
    tables, thresholds = stacked_tables(budget, capacity)
    monitor = RunMonitor(
        np.array([bank.t]),
        filters,
        means,
        covs,
        rows,
        tables,
        thresholds,
        jerk_density,
        fix_index(position),
    )
    return monitor, names


def after_run(bank: SeparationBank, monitor: RunMonitor, names: Sequence[str]) -> None:
    """Bring ``bank`` up to date with a run's ``monitor`` (:func:`run_monitor`'s, ``names`` its ids): its
    clock, its filters' arrays, and its ids when the run spawned or pruned (a new list, so that the
    bank's kept plan no longer applies)."""
    bank.t = float(monitor.clock[0])
    count = int(monitor.filters[0])
    bank.means, bank.covs = monitor.means[:count], monitor.covs[:count]
    codes = monitor.filters[1 : count + 1].tolist()
    if codes != list(range(len(bank.ids))):
        bank.ids = [names[code] for code in codes]
