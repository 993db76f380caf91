"""A run of usual epochs of an IMM/2IMM bank in one compiled call (``core.kernels_run``): its inputs and
the call on a ``CompiledBankStepper``'s constant arrays.

The per-epoch path (``CompiledBankStepper.step``, then the integrity bank's ``SeparationBank.epoch``)
costs two kernel calls an epoch and the Python around them; a run of epochs that need neither the
gate's nor the monitor's Python (``pipelines.rsu_imu_run`` decides which) costs one call for all, with
the same kernels in the same order, so the same results to the last bit."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from edgepos.core.compiled import CompiledBankStepper
from edgepos.core.kernels_grouping import group_epochs, write_records
from edgepos.core.updates import RsuGyroEpoch


class RunRows(NamedTuple):
    """A run's measurement rows, epoch after epoch, in ``kernels_run.run_epochs``'s order."""

    positions: np.ndarray
    observed: np.ndarray
    yaw_rates: np.ndarray
    range_variances: np.ndarray
    bearing_variances: np.ndarray
    range_std: np.ndarray
    bearing_std: np.ndarray


class RunMonitor(NamedTuple):
    """The integrity bank a run steps after each epoch (``core.integrity_run`` makes it from a
    ``SeparationBank`` and reads it back): its clock (one element, written back), its filters' count
    and RSU codes (``[K, 0, code_1, ..]``, written back), their means and covariances in the leading rows
    (room for the sub-filters the run may spawn; written in place), each measurement row's RSU code, the
    radial factor tables and test thresholds of a bank of 0, 1, .. sub-filters, the jerk density, and
    where x and y are in the fused mean."""

    clock: np.ndarray
    filters: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    rsu_codes: np.ndarray
    tables: np.ndarray
    thresholds: np.ndarray
    jerk_density: float
    fix_index: np.ndarray


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


#: A run without the monitor: arrays of the monitor's types (one compiled signature serves both: the
#: tables, thresholds and fix index read only, as ``core.integrity_run`` shares them between runs).
_NO_MONITOR = RunMonitor(
    np.zeros(1),
    np.zeros(2, dtype=np.int64),
    np.zeros((0, 6)),
    np.zeros((0, 6, 6)),
    np.zeros(0, dtype=np.int64),
    _read_only(np.zeros((1, 2, 1))),
    _read_only(np.zeros(1)),
    0.0,
    _read_only(np.zeros(2, dtype=np.int64)),
)


#: Magnitude below which every number a run's fix is made of keeps its fix finite: the fix's products
#: (the turn rate's vx * ay, over at least 0.01) and sums (speed, the weighted NIS) of such numbers stay
#: far below the largest float. A run stops before an epoch with a number beyond it (``kernels_run``).
FIX_INPUT_BOUND = 1e150


def run_epochs(
    stepper: CompiledBankStepper,
    means: np.ndarray,
    covs: np.ndarray,
    probabilities: np.ndarray,
    start: float,
    times: list[float],
    rsu_bounds: np.ndarray,
    gyro_bounds: np.ndarray,
    rows: RunRows,
    gyro_variance: float,
    min_speed: float,
    averaged: bool,
    thresholds: tuple[float, float],
    monitor: RunMonitor | None,
) -> tuple[int, np.ndarray, np.ndarray]:
    """A run of usual epochs from ``means``, ``covs``, ``probabilities`` at time ``start`` (only when
    ``stepper.runs``): epoch ``j`` at ``times[j]``, its measurements rows ``rsu_bounds[j]`` .. and
    ``gyro_bounds[j]`` .. of ``rows`` (int64 arrays, one bound more than epochs; the gyro's variance and
    the speed below which it is not used as every epoch's ``RsuGyroEpoch`` has them), the gate at
    ``thresholds`` as ``stepper.step`` takes them, and with a ``monitor`` the integrity bank stepped after
    each. Returns how many epochs were done (the run stops before the first that needs the per-epoch
    path), every epoch's output (``epoch_step``'s, a row each: read them with :func:`run_outputs` and
    :func:`posterior`) and protection level (with a monitor; those of the epochs done)."""
    from edgepos.core import kernels_run

    count, nc = stepper._sizes
    # a row wide enough for every epoch: the run's RSU pairs and gyro readings, all of them (no epoch has more)
    epochs = len(times)
    outs = np.empty((epochs, kernels_run.output_width(count, nc, len(rows.positions), len(rows.yaw_rates))))
    levels = np.empty(epochs)
    bank = monitor or _NO_MONITOR
    done = kernels_run.run_epochs(
        np.ascontiguousarray(means, dtype=float),
        np.ascontiguousarray(covs, dtype=float),
        np.ascontiguousarray(probabilities, dtype=float),
        stepper._transition,
        stepper._active,
        stepper._common,
        stepper._phi_slot,
        stepper._motion_kinds,
        stepper._motion_params,
        stepper._kinds,
        stepper._priority,
        stepper._others,
        stepper._filter_kind,
        stepper._weights,
        stepper._has_centre,
        start,
        rsu_bounds,
        gyro_bounds,
        *rows,
        gyro_variance,
        min_speed**2,
        averaged,
        thresholds[0],
        thresholds[1],
        monitor is not None,
        np.array(times),
        bank.clock,
        bank.filters,
        bank.means,
        bank.covs,
        bank.rsu_codes,
        bank.tables,
        bank.thresholds,
        bank.jerk_density,
        bank.fix_index,
        FIX_INPUT_BOUND,
        outs,
        levels,
    )
    return done, outs, levels


def run_outputs(
    stepper: CompiledBankStepper, outs: np.ndarray, done: int
) -> tuple[np.ndarray, np.ndarray, list[list[float]], list[float]]:
    """Per epoch done, from :func:`run_epochs`'s outputs: the fused means (done, nc) and covariances
    (done, nc, nc) (views), the model probabilities, and the models' NIS weighted by them. Read for all
    epochs at once, where a ``StepResult`` per epoch made five views and two objects each."""
    count, nc = stepper._sizes
    size = stepper._prediction_size  # each output: the prediction's part, then the correction's
    fused_at = size + 73 * count  # in the correction's: means, covs, probabilities, the fused mean and cov
    block = outs[:done]
    probabilities = block[:, fused_at - count : fused_at]
    nis = block[:, 2 * size + count : 2 * size + 2 * count]  # the tail: log-likelihoods, then NIS
    # as rsu_imu._step's probabilities.dot(nis), epoch by epoch: a matmul of row vectors by column vectors
    # calls numpy's same dot loop (DOUBLE_dot, BLAS ddot) on each pair, in one call for every epoch
    weighted = np.matmul(probabilities[:, None, :], nis[:, :, None]).reshape(done).tolist()
    means = block[:, fused_at : fused_at + nc]
    covs = block[:, fused_at + nc : fused_at + nc * (1 + nc)].reshape(done, nc, nc)
    return means, covs, probabilities.tolist(), weighted


def posterior(
    stepper: CompiledBankStepper, outs: np.ndarray, epoch: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Epoch ``epoch``'s corrected model means, covariances and probabilities from :func:`run_epochs`'s
    outputs (views of them): what the session keeps, without the ``StepResult`` around them."""
    means, covs, probabilities, _, _ = stepper._kernels.prediction_views(
        outs[epoch, stepper._prediction_size :], *stepper._sizes
    )
    return means, covs, probabilities


def warm_up_run(
    stepper: CompiledBankStepper, epoch: RsuGyroEpoch, means: np.ndarray, covs: np.ndarray
) -> None:
    """Compile (or load) ``kernels_run.run_epochs``: a run of two epochs of ``epoch``'s measurements; and
    ``kernels_grouping``'s ``group_epochs``, which groups a batch's observations into such epochs, and
    ``write_records``, which writes their lag-window records."""
    positions, observed, yaw_rates, range_variances, bearing_variances, gyro_variance = epoch.kernel_arrays
    arrays = (
        positions,
        observed,
        yaw_rates,
        range_variances,
        bearing_variances,
        epoch.range_std,
        epoch.bearing_std,
    )
    rsus, gyros = positions.shape[0], yaw_rates.shape[0]
    run_epochs(
        stepper,
        means,
        covs,
        np.full(means.shape[0], 1.0 / means.shape[0]),
        0.0,
        [0.05, 0.1],
        np.array([0, rsus, 2 * rsus], dtype=np.int64),
        np.array([0, gyros, 2 * gyros], dtype=np.int64),
        RunRows(*(np.ascontiguousarray(np.concatenate([a, a]), dtype=float) for a in arrays)),
        gyro_variance,
        epoch.gyro_min_speed,
        False,
        (5.99, 3.84),
        None,
    )
    table = np.array([[0.05, 1, 4.0, 1.4], [0.05, 0, 0.0, 0.0], [0.1, 1, 5.0, 1.2]])  # 2 RSUs, a gyro
    stations = np.array([[0.0] * 5, [0.0, 0.0, 0.6, 0.01, 160.0]])
    group_epochs(table, stations, 4, 4096)
    heads = (np.frombuffer(b"\x03rsu", np.uint8), np.frombuffer(b"\x04gyro", np.uint8))  # read only, as
    texts = np.frombuffer(b"\x01\x00A", np.uint8)  # pipelines.rsu_imu_batch.batch_records passes them
    write_records(table, texts, _read_only(np.array([0, 0, 3], dtype=np.int64)), *heads)
