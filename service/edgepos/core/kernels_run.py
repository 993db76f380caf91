"""A run of usual epochs in one compiled call: ``kernels_epoch.epoch_step`` for each, and the integrity
bank's ``kernels_integrity.bank_epoch`` after it when the monitor is on.

``run_epochs`` steps epoch after epoch, each from the posterior the one before wrote, exactly as the
per-epoch path does with the same kernels on the same arrays (so its results are that path's bit for
bit), and stops before the first epoch that needs Python: a measurement the gate would leave out, a
prediction or correction that failed (the numpy reference repairs or raises), an interval whose rounding
for F and Q only Python's ``round`` can tell (``rounded_dt``), and with the monitor a test that failed or
a fix without a bound. A level beyond the alert limit is not one: the bank steps
as in any epoch and the caller puts that fix in alarm. The epoch a run stops before leaves no trace: the
integrity bank's filters, their codes and its clock are as before it. The bank's own steps around the
epoch (``SeparationBank.epoch`` with ``prune``) are here on RSU codes (``core.integrity_run``): a
sub-filter spawned for an RSU coming into use, a new plan (the work vector of ``bank_epoch``) when the
filters or the RSUs in use change, and the converged sub-filters of RSUs out of use pruned. The caller
(``pipelines.rsu_imu_run``) makes the fixes of the epochs done and finishes the rest on the per-epoch
path. One call for a batch's run saves per epoch the Python around two calls (their arguments, their
result objects, the monitor's bookkeeping).

The run's measurement rows are concatenated: epoch ``j``'s RSU pairs are rows ``rsu_bounds[j]`` to
``rsu_bounds[j + 1]`` of ``positions`` .. ``bearing_std``, its gyro readings ``yaw_rates[gyro_bounds[j]
: gyro_bounds[j + 1]]`` (the rows of a whole batch, whose epochs before and after the run's are not read). ``outs[j]`` receives epoch ``j``'s ``epoch_step`` output (see there), ``levels[j]``
its protection level.
"""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.integrity_bank import CONVERGED, DROPPABLE, JERK, SCALARS, TABLE, THRESHOLD
from edgepos.core.kernels import _prediction_parts
from edgepos.core.kernels_base import OK, BoolArray, IntArray, _jit, _jit_nogil
from edgepos.core.kernels_epoch import epoch_step
from edgepos.core.kernels_integrity import bank_epoch, work_size
from edgepos.core.motion.base import DT_RESOLUTION_DECIMALS
from edgepos.core.numerics import FloatArray


@_jit_nogil
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
    start: float,
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
    bank_filters: IntArray,
    bank_means: FloatArray,
    bank_covs: FloatArray,
    rsu_codes: IntArray,
    tables: FloatArray,
    thresholds: FloatArray,
    jerk_density: float,
    fix_index: IntArray,
    fix_bound: float,
    outs: FloatArray,
    levels: FloatArray,
) -> int:
    """Step the run's epochs from ``means``, ``covs``, ``probabilities`` (see the module docstring);
    epoch ``j`` is at ``times[j]``, its interval from the epoch before (from ``start``, the time of
    ``means``, for the first), which ``epoch_step`` takes with its rounding for F and Q (:func:`rounded_dt`;
    an epoch whose rounding needs Python's is left to the per-epoch path). With ``monitored``, the integrity bank steps after each epoch as
    ``SeparationBank.epoch`` (with ``prune``) would: its clock ``bank_clock[0]``, its filters'
    count ``bank_filters[0]`` and RSU codes ``bank_filters[1:]`` (0: the reference), their means and
    covariances in the leading rows of ``bank_means`` and ``bank_covs`` (room for a sub-filter per RSU
    the run may bring into use), all written back. ``rsu_codes`` gives each measurement row's RSU
    code, ``tables[h]`` and ``thresholds[h]`` a bank of ``h`` sub-filters' radial factor tables and
    test threshold, ``fix_index`` where x and y are in the fused mean. An epoch whose fix would be made of
    a number of ``fix_bound`` or more in magnitude (its model probabilities, fused mean and covariance,
    log-likelihoods and NIS; NaN included) needs Python too: the per-epoch path checks its fix number by
    number, so a run's fixes need no such check (their products and sums cannot overflow).
    Returns the number of epochs done: those before the first that needs Python."""
    count = means.shape[0]
    nc = common.shape[0]
    size = 73 * count + nc * (1 + nc)  # the prediction's part of an output, then the correction's
    saved_means = bank_means.copy()
    saved_covs = bank_covs.copy()
    saved_filters = bank_filters.copy()
    work = np.zeros(1)
    planned = -1  # the epoch whose RSUs ``work`` was made for (-1: none yet)
    for j in range(times.shape[0]):
        dt = times[j] - (times[j - 1] if j > 0 else start)  # as the per-epoch path's t - filter_t
        step_dt = rounded_dt(dt)
        if math.isnan(step_dt):
            return j
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
            dt,
            step_dt,
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
        if status != OK or not _bounded(out[size + 72 * count : 2 * size + 2 * count], fix_bound):
            return j
        posterior = out[size : 2 * size + 2 * count]
        next_means, next_covs, next_probabilities, fused_mean, fused_cov = _prediction_parts(
            posterior, count, nc
        )
        if monitored:
            filters = bank_filters[0]
            saved_means[:filters] = bank_means[:filters]
            saved_covs[:filters] = bank_covs[:filters]
            saved_filters[:] = bank_filters
            codes = rsu_codes[first:last]
            if _spawn(bank_means, bank_covs, bank_filters, codes) or not _same_codes(
                rsu_codes, rsu_bounds, planned, j
            ):
                work = _plan_work(bank_filters, codes, tables, thresholds, jerk_density, fix_index)
                planned = j
            filters = bank_filters[0]
            t = times[j]
            level = bank_epoch(
                bank_means[:filters],
                bank_covs[:filters],
                work,
                t - bank_clock[0],
                positions[first:last],
                observed[first:last],
                range_std[first:last],
                bearing_std[first:last],
                fused_mean,
                fused_cov,
            )
            # a test failed or the update did (negative codes), or the fix has no bound (NaN, infinite)
            if not (level >= 0.0 and math.isfinite(level)):
                filters = saved_filters[0]
                bank_means[:filters] = saved_means[:filters]
                bank_covs[:filters] = saved_covs[:filters]
                bank_filters[:] = saved_filters
                return j
            if not bank_clock[0] > t:
                bank_clock[0] = t
            levels[j] = level
            if (
                work[DROPPABLE] != 0.0
                and not _covered(bank_filters, codes)
                and _prune(bank_means, bank_covs, bank_filters, codes)
            ):
                planned = -1  # the filters moved: the next epoch's owners and tables are new
        means, covs, probabilities = next_means, next_covs, next_probabilities
    return int(times.shape[0])


#: The decimals ``rounded_dt`` keeps, and the relative error bound of the product ``dt * 10**9`` it
#: rounds (half an ulp is 2**-53 of it; four times that, to be clear of it).
_NS_PER_S = 10.0**DT_RESOLUTION_DECIMALS
_PRODUCT_ERROR = 4.0 * 2.0**-53


@_jit
def rounded_dt(dt: float) -> float:
    """``motion.base.dt_key``'s rounding (Python's ``round(dt, 9)``, 0 for 0) to the bit, or NaN where
    only Python's can tell. Python rounds the exact decimal value of ``dt`` to 9 decimals, half to even,
    and reads that decimal back (the double nearest to it). The product ``y = dt * 1e9`` is within
    ``_PRODUCT_ERROR * |y|`` of the exact ``dt * 10**9``; unless that is as near a half between two integers,
    both round to the same integer ``n``, and ``n / 1e9`` (``n`` and ``1e9`` exact doubles, the quotient
    correctly rounded) is the double nearest to that decimal. NaN for such a near-half (some 4e-8 of
    intervals of 50 ms), for ``|y|`` of 2**52 or more (whole numbers already) and for a NaN ``dt``."""
    if dt == 0.0:
        return 0.0
    y = dt * _NS_PER_S
    if not abs(y) < 2.0**52:
        return math.nan
    n = float(np.rint(y))
    if not abs(abs(y - n) - 0.5) > _PRODUCT_ERROR * abs(y):
        return math.nan
    return n / _NS_PER_S


@_jit
def _bounded(values: FloatArray, bound: float) -> bool:
    """Whether every value is below ``bound`` in magnitude (False for NaN)."""
    for value in values:
        if not abs(value) < bound:
            return False
    return True


@_jit
def _has(bank_filters: IntArray, code: int) -> bool:
    """Whether a sub-filter leaves out the RSU of ``code``."""
    for k in range(1, bank_filters[0]):
        if bank_filters[1 + k] == code:
            return True
    return False


@_jit
def _spawn(bank_means: FloatArray, bank_covs: FloatArray, bank_filters: IntArray, codes: IntArray) -> bool:
    """``SeparationBank.spawn``: a copy of the reference for each RSU of ``codes`` without a sub-filter,
    in their order; whether any was made."""
    made = False
    for code in codes:
        if not _has(bank_filters, code):
            filters = bank_filters[0]
            bank_means[filters] = bank_means[0]
            bank_covs[filters] = bank_covs[0]
            bank_filters[1 + filters] = code
            bank_filters[0] = filters + 1
            made = True
    return made


@_jit
def _same_codes(rsu_codes: IntArray, rsu_bounds: IntArray, planned: int, j: int) -> bool:
    """Whether epoch ``j`` measures the RSUs of epoch ``planned`` in the same order (-1: none)."""
    if planned < 0:
        return False
    first, last = rsu_bounds[j], rsu_bounds[j + 1]
    before = rsu_bounds[planned]
    if last - first != rsu_bounds[planned + 1] - before:
        return False
    for i in range(last - first):
        if rsu_codes[first + i] != rsu_codes[before + i]:
            return False
    return True


@_jit
def _covered(bank_filters: IntArray, codes: IntArray) -> bool:
    """Whether every sub-filter's RSU is among ``codes`` (``integrity_bank._covered``)."""
    for k in range(1, bank_filters[0]):
        found = False
        for code in codes:
            if code == bank_filters[1 + k]:
                found = True
        if not found:
            return False
    return True


@_jit
def _plan_work(
    bank_filters: IntArray,
    codes: IntArray,
    tables: FloatArray,
    thresholds: FloatArray,
    jerk_density: float,
    fix_index: IntArray,
) -> FloatArray:
    """``bank_epoch``'s work vector for the bank's filters and these RSUs in use, as
    ``integrity_bank._plan_work`` makes it (no RSU excluded: a run has none)."""
    filters = bank_filters[0]
    n = codes.shape[0]
    table = tables.shape[2]
    work = np.zeros(work_size(n, filters, table))
    work[JERK], work[THRESHOLD], work[TABLE] = jerk_density, thresholds[filters - 1], table
    work[SCALARS : SCALARS + table] = tables[filters - 1, 0]
    work[SCALARS + table : SCALARS + 2 * table] = tables[filters - 1, 1]
    start = SCALARS + 2 * table
    for i in range(n):
        owner = -1
        for k in range(1, filters):
            if bank_filters[1 + k] == codes[i]:
                owner = k
        work[start + i] = owner
    work[start + n + filters] = fix_index[0]
    work[start + n + filters + 1] = fix_index[1]
    return work


@_jit
def _prune(bank_means: FloatArray, bank_covs: FloatArray, bank_filters: IntArray, codes: IntArray) -> bool:
    """``SeparationBank.prune`` for the RSUs of ``codes``: drop the sub-filters whose RSU is not in use
    and whose position covariance (trace) exceeds the reference's by no more than ``CONVERGED`` of it,
    the rest moved up in order; whether any was dropped."""
    reference = bank_covs[0, 0, 0] + bank_covs[0, 3, 3]
    bound = CONVERGED * reference
    kept = 1
    for k in range(1, bank_filters[0]):
        code = bank_filters[1 + k]
        in_use = False
        for used in codes:
            if used == code:
                in_use = True
        if in_use or (bank_covs[k, 0, 0] + bank_covs[k, 3, 3]) - reference > bound:
            if kept != k:
                bank_means[kept] = bank_means[k]
                bank_covs[kept] = bank_covs[k]
                bank_filters[1 + kept] = code
            kept += 1
    dropped = bool(kept < bank_filters[0])
    bank_filters[0] = kept
    return dropped


def output_width(count: int, nc: int, rsus: int, gyros: int) -> int:
    """The length of one epoch's row of ``outs``: ``epoch_step``'s output for the most RSU pairs and
    gyro readings of any epoch of the run."""
    size = 73 * count + nc * (1 + nc)
    return 2 * size + 2 * count + rsus + gyros
