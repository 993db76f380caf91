"""A run of usual epochs in one compiled call: ``kernels_epoch.epoch_step`` for each, and the integrity
bank's ``kernels_integrity.bank_epoch`` after it when the monitor is on.

``run_epochs`` steps epoch after epoch, each from the posterior the one before wrote, exactly as the
per-epoch path does with the same kernels on the same arrays (so its results are that path's bit for
bit), and stops before the first epoch that needs Python: a measurement the gate would leave out, a
prediction or correction that failed (the numpy reference repairs or raises), and with the monitor a
test that failed or a fix without a bound or beyond the alert limit. That epoch leaves no trace: the
integrity bank's arrays, its clock and its plan's work vector are as before it. An epoch after which the bank has sub-filters to
prune ends the run after it, with ``bank_clock[1]`` set: the caller prunes, as ``SeparationBank.epoch``
does after such an epoch. The caller
(``pipelines.rsu_imu_run``) makes the fixes of the epochs done and finishes the rest on the per-epoch
path. One call for a batch's run saves per epoch the Python around two calls (their arguments, their
result objects, the monitor's bookkeeping).

The run's measurement rows are concatenated: epoch ``j``'s RSU pairs are rows ``rsu_bounds[j]`` to
``rsu_bounds[j + 1]`` of ``positions`` .. ``bearing_std``, its gyro readings ``yaw_rates[gyro_bounds[j]
: gyro_bounds[j + 1]]``. ``outs[j]`` receives epoch ``j``'s ``epoch_step`` output (see there), ``levels[j]``
its protection level.
"""

from __future__ import annotations

from edgepos.core.integrity_bank import DROPPABLE
from edgepos.core.kernels import _prediction_parts
from edgepos.core.kernels_base import OK, BoolArray, IntArray, _jit
from edgepos.core.kernels_epoch import epoch_step
from edgepos.core.kernels_integrity import bank_epoch
from edgepos.core.numerics import FloatArray


@_jit
def run_epochs(
    means: FloatArray,
    covs: FloatArray,
    probabilities: FloatArray,
    transition: FloatArray,
    active: BoolArray,
    common: IntArray,
    phi_slot: int,
    motion_kinds: IntArray,
    motion_params: FloatArray,
    kinds: IntArray,
    priority: IntArray,
    others: IntArray,
    filter_kind: int,
    weights: FloatArray,
    has_centre: bool,
    dts: FloatArray,
    step_dts: FloatArray,
    rsu_bounds: IntArray,
    gyro_bounds: IntArray,
    positions: FloatArray,
    observed: FloatArray,
    yaw_rates: FloatArray,
    range_variances: FloatArray,
    bearing_variances: FloatArray,
    range_std: FloatArray,
    bearing_std: FloatArray,
    gyro_variance: float,
    min_speed_sq: float,
    averaged: bool,
    rsu_threshold: float,
    gyro_threshold: float,
    monitored: bool,
    times: FloatArray,
    bank_clock: FloatArray,
    bank_means: FloatArray,
    bank_covs: FloatArray,
    work: FloatArray,
    alert_limit: float,
    covered: bool,
    outs: FloatArray,
    levels: FloatArray,
) -> int:
    """Step the run's epochs from ``means``, ``covs``, ``probabilities`` (see the module docstring);
    ``dts[j]`` and ``step_dts[j]`` are epoch ``j``'s interval and its rounding for F and Q, as
    ``epoch_step`` takes them. With ``monitored``, the bank (``bank_means``, ``bank_covs``, its clock
    ``bank_clock[0]``, the prune flag ``bank_clock[1]`` and its plan's ``work``) steps after each epoch as ``SeparationBank.epoch`` would.
    Returns the number of epochs done: those before the first that needs Python."""
    count = means.shape[0]
    nc = common.shape[0]
    size = 73 * count + nc * (1 + nc)  # the prediction's part of an output, then the correction's
    saved_means = bank_means.copy()
    saved_covs = bank_covs.copy()
    saved_work = work.copy()  # the plan's vector: its outcome and scratch, as the call before left them
    for j in range(dts.shape[0]):
        first, last = rsu_bounds[j], rsu_bounds[j + 1]
        out = outs[j]
        status = epoch_step(
            means,
            covs,
            probabilities,
            transition,
            active,
            common,
            phi_slot,
            dts[j],
            step_dts[j],
            motion_kinds,
            motion_params,
            kinds,
            priority,
            others,
            positions[first:last],
            observed[first:last],
            yaw_rates[gyro_bounds[j] : gyro_bounds[j + 1]],
            range_variances[first:last],
            bearing_variances[first:last],
            gyro_variance,
            min_speed_sq,
            averaged,
            rsu_threshold,
            gyro_threshold,
            filter_kind,
            weights,
            has_centre,
            out,
        )
        if status != OK:
            return j
        posterior = out[size : 2 * size + 2 * count]
        next_means, next_covs, next_probabilities, fused_mean, fused_cov = _prediction_parts(
            posterior, count, nc
        )
        if monitored:
            saved_means[:] = bank_means
            saved_covs[:] = bank_covs
            saved_work[:] = work
            t = times[j]
            level = bank_epoch(
                bank_means,
                bank_covs,
                work,
                t - bank_clock[0],
                positions[first:last],
                observed[first:last],
                range_std[first:last],
                bearing_std[first:last],
                fused_mean,
                fused_cov,
            )
            if not 0.0 <= level <= alert_limit:
                bank_means[:] = saved_means
                bank_covs[:] = saved_covs
                work[:] = saved_work
                return j
            if not bank_clock[0] > t:
                bank_clock[0] = t
            levels[j] = level
            if not covered and work[DROPPABLE] != 0.0:
                bank_clock[1] = (
                    1.0  # sub-filters to prune after this epoch: the caller's, as SeparationBank.epoch
                )
                return j + 1
        means, covs, probabilities = next_means, next_covs, next_probabilities
    return int(dts.shape[0])


def output_width(count: int, nc: int, rsus: int, gyros: int) -> int:
    """The length of one epoch's row of ``outs``: ``epoch_step``'s output for the most RSU pairs and
    gyro readings of any epoch of the run."""
    size = 73 * count + nc * (1 + nc)
    return 2 * size + 2 * count + rsus + gyros
