"""Runs of usual ``rsu_imu`` epochs in one compiled call, and the gate's and records' small caches the
per-epoch step shares.

An epoch is usual when the filter is initialised and steps on the compiled kernels, it has an RSU in
view, it comes within ``max_gap`` of the one before and, with the integrity monitor on, the monitor
holds no RSU out. ``run_fixes`` hands a run of such epochs to ``core.compiled_run.run_epochs``
(``core.kernels_run``), which steps them with the same kernels as the per-epoch path
(``rsu_imu._step``), the monitor's bank with them (``core.integrity_run``: the kernel spawns a
sub-filter where an RSU comes into use, prunes and makes a new plan where ``SeparationBank.epoch``
would), and stops before the first epoch that needs that path (a measurement the gate leaves out, a
failed step, a failed integrity test, a fix without a bound); then makes their fixes as ``_step``
does, in alarm where the protection level exceeds the alert limit (the bank steps as in any other
epoch). The fixes and the state are the per-epoch path's bit for bit
(tests/pipelines/test_rsu_imu_run.py compares, and bench/rsu_imu_digest.py).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import TYPE_CHECKING, cast

import numpy as np
from scipy.stats import chi2

from edgepos.core import integrity_run, layout
from edgepos.core.compiled import BankStepper, CompiledBankStepper
from edgepos.core.compiled_run import RunRows, posterior, run_epochs, run_outputs
from edgepos.core.imm import InteractingMultipleModel
from edgepos.core.integrity import ALARM, OK, UNAVAILABLE
from edgepos.core.observations import Observation
from edgepos.core.updates import GYRO_MIN_SPEED, measurement_dim
from edgepos.pipelines.base import Fix, MeasurementUse
from edgepos.pipelines.integrity import _monitor_of, _position_index
from edgepos.pipelines.rsu_imu_batch import USED_KEPT, BatchEpochs
from edgepos.pipelines.rsu_imu_fix import fix_form, fix_layout, has_acceleration

if TYPE_CHECKING:  # the session type only: rsu_imu imports this module
    from edgepos.pipelines.rsu_imu import _SessionState

#: Runs shorter than this go the per-epoch path: one epoch gains less than the run's call costs.
MIN_RUN = 2

#: ``BankStepper.step``'s thresholds when nothing is gated.
UNGATED = (-1.0, -1.0)


@functools.lru_cache(maxsize=64)
def gate_threshold(probability: float, dof: int) -> float:
    """The chi-square quantile a squared Mahalanobis distance is gated at."""
    return float(chi2.ppf(probability, dof))


@functools.lru_cache(maxsize=64)
def gate_thresholds(probability: float, components: tuple[int, ...]) -> tuple[float, float]:
    """The gate's thresholds of an RSU pair and of a gyro reading (-1: gyros not gated, as ``_gate``
    leaves them when the output lacks an acceleration) for ``BankStepper.step``."""
    gyros = layout.XA in components and layout.YA in components
    return gate_threshold(probability, 2), gate_threshold(probability, 1) if gyros else -1.0


_USED: dict[str, list[MeasurementUse]] = {}


def used_records(kind: str, count: int) -> list[MeasurementUse]:
    """The records of measurements ``0 .. count - 1`` of ``kind`` that entered the filter, by index (at
    least ``min(count, USED_KEPT)`` of them): a run's epochs index this list instead of calling ``used``
    per measurement."""
    records = _USED.get(kind, [])
    wanted = min(count, USED_KEPT)
    if len(records) < wanted:  # a longer list in place of the old (threads racing here each get a whole one)
        records = _USED[kind] = records + [MeasurementUse(i, kind, True) for i in range(len(records), wanted)]
    return records


def used(index: int, kind: str) -> MeasurementUse:
    """The record of a measurement that entered the filter (immutable, so one instance serves every fix)."""
    if index < USED_KEPT:
        return used_records(kind, index + 1)[index]
    return MeasurementUse(index, kind, True)


@functools.lru_cache(maxsize=64)
def kinematic_entries(components: tuple[int, ...]) -> np.ndarray:
    """Where the kinematic block (x, y, vx, vy: ``fix_layout``'s order) of a covariance over
    ``components`` lies in the covariance's flattened rows, row by row: one ``take`` gives every
    epoch's block (read only: the cache shares it)."""
    kinematic = fix_layout(components)[0]
    size = len(components)
    entries = np.array([i * size + j for i in kinematic for j in kinematic], dtype=np.intp)
    entries.flags.writeable = False
    return entries


@functools.cache
def _record_table() -> np.ndarray:
    """``used_records`` of both kinds as one object array, rsu then gyro: what ``BatchEpochs.slots``
    index (read only: the cache shares it)."""
    table = np.empty(2 * USED_KEPT, dtype=object)
    table[:USED_KEPT] = used_records("rsu", USED_KEPT)
    table[USED_KEPT:] = used_records("gyro", USED_KEPT)
    table.flags.writeable = False
    return table


def fix_records(epochs: BatchEpochs, observations: Sequence[Observation]) -> list[MeasurementUse]:
    """The record of each observation of the batch in a run's fix, by position in ``epochs.order``: the
    used record of each RSU and gyro the epochs use, the own record of each RSU they leave out."""
    records: list[MeasurementUse] = _record_table().take(epochs.slots).tolist()
    order = epochs.order
    if epochs.uses or len(order) > USED_KEPT:  # a slot of -1 (its record taken from the table's end)
        for position in np.flatnonzero(epochs.slots < 0).tolist():
            i = order[position]
            left_out = epochs.uses.get(i)
            records[position] = used(i, observations[i].kind) if left_out is None else left_out
    return records


def run_fixes(
    session: _SessionState,
    bank: InteractingMultipleModel,
    stepper: BankStepper,
    epochs: BatchEpochs,
    first: int,
    observations: Sequence[Observation],
) -> list[Fix]:
    """The fixes of the usual epochs from epoch ``first`` on, stepped in one compiled call, with the
    session (and its integrity bank) advanced past them; none when fewer than ``MIN_RUN`` qualify. The
    fixes are finite: the run stops before an epoch whose fix could hold NaN or infinity
    (``compiled_run.FIX_INPUT_BOUND``), which the per-epoch path checks."""
    options = session.options
    if not (stepper.runs and session.initialised and session.filter_t is not None):
        return []
    if not has_acceleration(bank.common):  # the turn rate then comes from the models' states: per epoch
        return []
    monitored = bool(options["integrity"])
    integrity_bank = session.integrity_bank
    if monitored and (integrity_bank is None or integrity_bank.excluded):
        return []
    max_gap = options["max_gap"]
    last_t: float = session.filter_t
    starts = epochs.starts
    count = 0
    for k in range(first, len(epochs)):
        t = epochs.times[k]
        if starts[k] == starts[k + 1] or t - last_t > max_gap:  # no RSU in view, or a gap
            break
        count += 1
        last_t = t
    if count < MIN_RUN:
        return []
    end = first + count
    times = epochs.times[first:end]
    rows = epochs.rows  # the batch's: its epochs' rows and where each starts
    gate = options["gate_probability"]
    run_monitor = names = None
    alert_limit = 0.0
    if integrity_bank is not None and monitored:
        monitor, jerk_density = _monitor_of(options)
        station_ids = [None if station is None else station.id for station in rows.station_list]
        run_monitor, names = integrity_run.run_monitor(
            integrity_bank,
            station_ids,
            rows.stations,
            monitor.budget,
            jerk_density,
            _position_index(bank.common),
        )
        alert_limit = monitor.budget.alert_limit
    compiled = cast(CompiledBankStepper, stepper)
    done, outs, levels = run_epochs(
        compiled,
        session.means,
        session.covs,
        session.probabilities,
        session.filter_t,
        times,
        rows.starts[first : end + 1],
        rows.gyro_starts[first : end + 1],
        RunRows(
            rows.positions,
            rows.observed,
            rows.yaw_rates,
            rows.range_variances,
            rows.bearing_variances,
            rows.range_std,
            rows.bearing_std,
        ),
        float(rows.gyro_std**2),  # as every epoch's RsuGyroEpoch has it (core.updates.new_epoch)
        GYRO_MIN_SPEED,
        rows.averaged,
        gate_thresholds(gate, bank.common) if gate > 0.0 else UNGATED,
        run_monitor,
    )
    if not done:  # the first epoch needs the per-epoch path (the bank is as it was)
        return []
    means, covs, probabilities, nis = run_outputs(compiled, outs, done)
    components = bank.common
    models = options["models"]
    # every epoch's lists at once: the covariance's rows, and its kinematic and position blocks
    kinematic_covs = covs.reshape(done, -1).take(kinematic_entries(components), 1).reshape(done, 4, 4)
    # the epochs' records: one for each index of an epoch, in ascending order (group_epochs's)
    records = fix_records(epochs, observations)
    bounds, gyro_starts = epochs.bounds, epochs.gyro_starts
    form = fix_form(components)
    fixes = []
    for k, t, mean, state_cov, kinematic_cov, position_cov, weights, weighted, level in zip(
        range(first, end),
        times,
        means.tolist(),
        covs.tolist(),
        kinematic_covs.tolist(),
        kinematic_covs[:, :2, :2].tolist(),
        probabilities,
        nis,
        levels.tolist(),
    ):
        if run_monitor is None:
            protection_level, integrity = None, UNAVAILABLE
        else:  # a level that passed every test, stated as SeparationBank.epoch's Protection states it
            protection_level, integrity = level, OK if level <= alert_limit else ALARM
        fixes.append(
            form.fix(
                t,
                "tracking",
                mean,
                state_cov,
                dict(zip(models, weights)),
                records[bounds[k] : bounds[k + 1]],
                weighted,
                measurement_dim(
                    starts[k + 1] - starts[k], gyro_starts[k + 1] - gyro_starts[k], rows.averaged
                ),
                protection_level,
                integrity,
                None,  # the run's outputs have both accelerations (checked above): no carried turn rate
                kinematic_cov,
                position_cov,
            )
        )
    session.means, session.covs, session.probabilities = posterior(compiled, outs, done - 1)
    session.t = session.filter_t = times[done - 1]
    session.epochs += done
    if integrity_bank is not None and run_monitor is not None and names is not None:
        integrity_run.after_run(integrity_bank, run_monitor, names)
    return fixes
