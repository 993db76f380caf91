"""A batch of RSU and gyro observations grouped into epochs in one compiled call: what
``pipelines.rsu_imu_batch.batch_epochs`` does with ``pipelines.epochs.group_by_time`` and ``epoch_parts``
per epoch (the readable reference, which the tests hold this kernel to), without a Python object per
epoch.

``group_epochs`` sorts the observations by time (stable: an epoch keeps the batch's order), splits them
where the time changes, and per epoch lists its gyros and its RSU observations inside their radius, the
nearest ``max_rsus`` of them by measured range (a stable sort, as Python's ``list.sort``), the others
marked as out of radius or not among the nearest."""

from __future__ import annotations

import numpy as np

from edgepos.core.kernels_base import IntArray, _jit
from edgepos.core.numerics import FloatArray

#: ``group_epochs``'s status of an observation: an RSU it uses, a gyro, an RSU beyond its
#: communication radius, an RSU in it but not among the nearest ``max_rsus``.
USED_RSU, GYRO, BEYOND_RADIUS, NOT_NEAREST = 0, 1, 2, 3


@_jit
def group_epochs(
    times: FloatArray,
    observed: FloatArray,
    station_table: FloatArray,
    station_codes: IntArray,
    max_rsus: int,
    kept: int,
) -> tuple[IntArray, IntArray, IntArray, IntArray, IntArray, IntArray, IntArray, IntArray]:
    """The epochs of a batch of ``n`` observations whose times are finite: observation ``i`` at
    ``times[i]``, its measured range ``observed[i, 0]`` and its station ``station_codes[i]`` (0: a gyro),
    whose radius is ``station_table[code, 4]``.

    Returns ``order`` (the observations in time order), ``bounds`` (epoch ``k`` is ``order[bounds[k] :
    bounds[k + 1]]``), ``rows`` and ``starts`` (epoch ``k``'s RSUs in use, nearest first, are
    ``rows[starts[k] : starts[k + 1]]``), ``gyro_rows`` and ``gyro_starts`` (its gyros, likewise),
    ``status`` (each observation's, by its index: ``USED_RSU`` .. ``NOT_NEAREST``) and ``slots`` (per
    position of ``order``: ``status * kept + index`` for an observation used, an RSU or a gyro, with an
    index below ``kept``; -1 for any other)."""
    n = times.shape[0]
    order = np.argsort(times, kind="mergesort")  # stable, as sorted() is
    bounds = np.empty(n + 1, dtype=np.int64)
    starts = np.empty(n + 1, dtype=np.int64)
    gyro_starts = np.empty(n + 1, dtype=np.int64)
    rows = np.empty(n, dtype=np.int64)
    gyro_rows = np.empty(n, dtype=np.int64)
    status = np.empty(n, dtype=np.int64)
    slots = np.empty(n, dtype=np.int64)
    candidates = np.empty(n, dtype=np.int64)  # the current epoch's RSUs inside their radius
    epochs = used = gyros = 0
    count = 0
    last = 0.0
    for position in range(n + 1):
        i = order[position] if position < n else -1
        if position == n or position == 0 or times[i] != last:
            if position > 0:  # the epoch before is complete: its nearest RSUs, stably by range
                for a in range(1, count):
                    moving = candidates[a]
                    measured = observed[moving, 0]
                    b = a
                    while b > 0 and observed[candidates[b - 1], 0] > measured:
                        candidates[b] = candidates[b - 1]
                        b -= 1
                    candidates[b] = moving
                for a in range(count):
                    if a < max_rsus:
                        rows[used] = candidates[a]
                        used += 1
                    else:
                        status[candidates[a]] = NOT_NEAREST
                count = 0
            if position == n:
                break
            bounds[epochs] = position
            starts[epochs] = used
            gyro_starts[epochs] = gyros
            epochs += 1
            last = times[i]
        code = station_codes[i]
        if code == 0:
            gyro_rows[gyros] = i
            gyros += 1
            status[i] = GYRO
        elif observed[i, 0] > station_table[code, 4]:
            status[i] = BEYOND_RADIUS
        else:
            candidates[count] = i
            count += 1
            status[i] = USED_RSU
    bounds[epochs] = n
    starts[epochs] = used
    gyro_starts[epochs] = gyros
    for position in range(n):
        i = order[position]
        slots[position] = status[i] * kept + i if status[i] <= GYRO and i < kept else -1
    return (
        order,
        bounds[: epochs + 1],
        rows[:used],
        starts[: epochs + 1],
        gyro_rows[:gyros],
        gyro_starts[: epochs + 1],
        status,
        slots,
    )
