"""A batch of RSU and gyro observations grouped into epochs, with the measurement rows a run of epochs
takes, in one compiled call: what ``pipelines.rsu_imu_batch.reference_epochs`` does with
``pipelines.epochs.group_by_time`` and ``epoch_parts`` per epoch and a ``take`` per array (the readable
reference, which the tests hold this kernel to), without a Python object per epoch.

``group_epochs`` sorts the observations by time (stable: an epoch keeps the batch's order), splits them
where the time changes, and per epoch lists its gyros and its RSU observations inside their radius, the
nearest ``max_rsus`` of them by measured range (a stable sort, as Python's ``list.sort``), the others
marked as out of radius or not among the nearest; then copies the rows of the RSUs and gyros in use,
epoch after epoch, as ``core.kernels_run.run_epochs`` takes them. ``write_records`` writes the batch's
lag-window records from the same table, byte for byte what ``core.observation_codec``'s encoders write
from the observations (``pipelines.rsu_imu_batch.batch_records`` checks the layout)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from edgepos.core.kernels_base import IntArray, _jit
from edgepos.core.numerics import FloatArray

#: ``group_epochs``'s slot of an observation it does not use: an index past the kept records, an RSU
#: beyond its communication radius, an RSU in it but not among the nearest ``max_rsus``.
PAST_KEPT, BEYOND_RADIUS, NOT_NEAREST = -1, -2, -3


@_jit
def group_epochs(
    table: FloatArray, station_table: FloatArray, max_rsus: int, kept: int
) -> tuple[
    FloatArray,
    IntArray,
    IntArray,
    IntArray,
    IntArray,
    FloatArray,
    FloatArray,
    FloatArray,
    FloatArray,
    FloatArray,
    FloatArray,
    FloatArray,
]:
    """The epochs of a batch of ``n`` observations (``pipelines.rsu_imu_batch.Batch``): observation
    ``i``'s time ``table[i, 0]`` (finite), its station ``table[i, 1]`` (0: a gyro), its two measured
    numbers ``table[i, 2:4]`` (range and bearing, or yaw rate and 0); station ``c``'s x, y, range and
    bearing standard deviations and radius ``station_table[c]``.

    Returns, of the ``E`` epochs in time order:

    * ``times`` (E): each epoch's time;
    * ``bounds`` (3, E + 1): epoch ``k``'s observations are ``order[bounds[0, k] : bounds[0, k + 1]]``,
      its RSUs in use rows ``bounds[1, k]`` to ``bounds[1, k + 1]``, its gyros ``bounds[2, k]`` to
      ``bounds[2, k + 1]``;
    * ``order_slots`` (2, n): ``order``, the observations in time order, and per position of it the
      slot of the observation's record in a run's fix: ``kind * kept + index`` (kind 0 an RSU in use, 1
      a gyro) when its index is below ``kept``, else ``PAST_KEPT``, ``BEYOND_RADIUS`` or
      ``NOT_NEAREST``;
    * ``indices`` (R + G): the observations of the R RSU rows (each epoch's nearest first), then of the
      G gyro rows; ``stations`` (R): the RSU rows' stations;
    * the rows: ``positions`` and ``observed`` (R, 2), ``range_std``, ``bearing_std`` and their squares
      ``range_variances``, ``bearing_variances`` (R), ``yaw_rates`` (G)."""
    n = table.shape[0]
    order_slots = np.empty((2, n), dtype=np.int64)
    order = order_slots[0]
    order[:] = np.argsort(table[:, 0], kind="mergesort")  # stable, as sorted() is
    slots = order_slots[1]
    bounds = np.empty((3, n + 1), dtype=np.int64)
    epoch_times = np.empty(n)
    rows = np.empty(n, dtype=np.int64)  # the RSUs in use
    gyro_rows = np.empty(n, dtype=np.int64)
    status = np.empty(n, dtype=np.int64)  # by index: 0 in use, 1 a gyro, else a slot of one not used
    candidates = np.empty(n, dtype=np.int64)  # the current epoch's RSUs inside their radius
    epochs = used = gyros = 0
    count = 0
    last = 0.0
    for position in range(n + 1):
        i = order[position] if position < n else -1
        if position == n or position == 0 or table[i, 0] != last:
            if position > 0:  # the epoch before is complete: its nearest RSUs, stably by range
                for a in range(1, count):
                    moving = candidates[a]
                    measured = table[moving, 2]
                    b = a
                    while b > 0 and table[candidates[b - 1], 2] > measured:
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
            bounds[0, epochs] = position
            bounds[1, epochs] = used
            bounds[2, epochs] = gyros
            last = epoch_times[epochs] = table[i, 0]
            epochs += 1
        code = int(table[i, 1])
        if code == 0:
            gyro_rows[gyros] = i
            gyros += 1
            status[i] = 1
        elif table[i, 2] > station_table[code, 4]:
            status[i] = BEYOND_RADIUS
        else:
            candidates[count] = i
            count += 1
            status[i] = 0
    bounds[0, epochs] = n
    bounds[1, epochs] = used
    bounds[2, epochs] = gyros
    for position in range(n):
        i = order[position]
        kind = status[i]
        slots[position] = kind if kind < 0 else (kind * kept + i if i < kept else PAST_KEPT)
    indices = np.empty(used + gyros, dtype=np.int64)
    indices[:used] = rows[:used]
    indices[used:] = gyro_rows[:gyros]
    stations = np.empty(used, dtype=np.int64)
    positions = np.empty((used, 2))
    observed = np.empty((used, 2))
    range_std = np.empty(used)
    bearing_std = np.empty(used)
    range_variances = np.empty(used)
    bearing_variances = np.empty(used)
    for row in range(used):
        i = rows[row]
        code = int(table[i, 1])
        stations[row] = code
        positions[row, 0] = station_table[code, 0]
        positions[row, 1] = station_table[code, 1]
        observed[row, 0] = table[i, 2]
        observed[row, 1] = table[i, 3]
        range_std[row] = station_table[code, 2]
        bearing_std[row] = station_table[code, 3]
        range_variances[row] = range_std[row] * range_std[row]  # np.square's product
        bearing_variances[row] = bearing_std[row] * bearing_std[row]
    yaw_rates = np.empty(gyros)
    for row in range(gyros):
        yaw_rates[row] = table[gyro_rows[row], 2]
    return (
        epoch_times[:epochs].copy(),
        bounds[:, : epochs + 1].copy(),
        order_slots,
        indices,
        stations,
        positions,
        observed,
        range_std,
        bearing_std,
        range_variances,
        bearing_variances,
        yaw_rates,
    )


@_jit
def write_records(
    table: FloatArray,
    texts: npt.NDArray[np.uint8],
    text_offsets: IntArray,
    rsu_head: npt.NDArray[np.uint8],
    gyro_head: npt.NDArray[np.uint8],
) -> tuple[npt.NDArray[np.uint8], IntArray]:
    """The lag window's records of a batch's observations (``table`` as ``group_epochs`` reads it), back
    to back in the batch's order, in ``core.observation_codec``'s layout: an RSU observation's
    ``rsu_head``, its time, range and bearing as little-endian float64 and its station's text field
    (``texts[text_offsets[code] : text_offsets[code + 1]]``); a gyro's ``gyro_head``, its time and yaw
    rate. Returns the bytes and where each observation's record ends. A little-endian machine's."""
    n = table.shape[0]
    ends = np.empty(n, dtype=np.int64)
    size = 0
    for i in range(n):
        code = int(table[i, 1])
        if code == 0:
            size += gyro_head.shape[0] + 16
        else:
            size += rsu_head.shape[0] + 24 + text_offsets[code + 1] - text_offsets[code]
        ends[i] = size
    written = np.empty(size, dtype=np.uint8)
    number = np.empty(1)
    raw = number.view(np.uint8)  # the float64's bytes, in the machine's order
    at = 0
    for i in range(n):  # byte by byte: a slice's copy costs more than these few bytes
        code = int(table[i, 1])
        head = gyro_head if code == 0 else rsu_head
        for b in range(head.shape[0]):
            written[at + b] = head[b]
        at += head.shape[0]
        for column in range(3 if code else 2):
            number[0] = table[i, 0 if column == 0 else column + 1]
            for b in range(8):
                written[at + b] = raw[b]
            at += 8
        if code:
            for b in range(text_offsets[code], text_offsets[code + 1]):
                written[at] = texts[b]
                at += 1
    return written, ends
