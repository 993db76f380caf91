"""A batch of ``rsu_imu`` observations as its epochs read them: checked once (``read_batch``), its rows as
arrays (``Batch``), and per epoch the RSUs in view and the gyros (``epoch_parts``) and their measurement
arrays (``epoch_measurements``); ``batch_epochs`` gives every epoch's at once, as flat lists and arrays
(``BatchEpochs``) from one compiled call (``core.kernels_grouping``), with ``reference_epochs`` the
readable reference. Reading the batch once makes an epoch's arrays a few index operations instead of
arrays built from Python lists; grouping it in one call makes no Python object per epoch (a 20-epoch
batch: about 1.2 us an epoch less than grouping, selecting and listing epoch by epoch, docs/benchmarks.md)."""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.kernels_grouping import BEYOND_RADIUS, GYRO, USED_RSU, group_epochs
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.core.updates import RsuGyroEpoch, new_epoch
from edgepos.pipelines.base import Environment, MeasurementUse, PipelineInputError, Problem, Rsu
from edgepos.pipelines.epochs import group_by_time

#: The most measurement indices whose records a run takes by slot (``BatchEpochs.slots``) and
#: ``rsu_imu_run.used`` keeps per kind.
USED_KEPT = 4096


class Batch:
    """A batch's observations as the epochs read them: each RSU observation's station, and per
    observation its row of the measurement arrays (station position, range and bearing, their noise
    standard deviations with the options' defaults filled in, the communication radius; a gyro's station
    numbers are zeros) and the gyro's yaw rate. Read once per batch (``read_batch``), so that an epoch's measurement
    arrays are a few index operations instead of array building from Python lists.

    Made of the batch's stations (``stations[0]`` None, a gyro's; five numbers each in
    ``station_rows``: x, y, range and bearing standard deviations, radius), each observation's station
    (``codes``) and its two measured numbers (``rows``: range and bearing, or a gyro's yaw rate and 0; so
    ``yaw_rates`` is each row's first number, of which only the gyros' are read): a station's numbers
    are listed once per batch (``station_table``), not once per observation, and taken per observation
    in one ``take``; and each observation's time (``times``), which ``batch_epochs`` groups by."""

    __slots__ = (
        "bearing_std",
        "bearing_variances",
        "codes",
        "observed",
        "positions",
        "range_std",
        "range_variances",
        "station_codes",
        "station_table",
        "stations",
        "times",
        "yaw_rates",
    )

    def __init__(
        self,
        stations: list[Rsu | None],
        station_rows: list[float],
        codes: list[int],
        rows: list[float],
        times: list[float],
    ) -> None:
        self.stations, self.codes = stations, codes
        count = len(codes)
        # flat lists: half the time of tuples; columns as views of the tables: every use takes rows of
        # them (``take``), which makes new C-contiguous arrays for the kernels, so copying each column
        # first only cost time
        table = np.array(rows, dtype=float).reshape(count, 2)
        self.station_codes = np.array(codes, np.intp)  # ``codes`` as an array: what rows of stations take
        self.station_table = np.array(station_rows, dtype=float).reshape(len(stations), 5)
        station = self.station_table.take(self.station_codes, 0)
        self.positions = station[:, 0:2]
        self.observed = table
        self.range_std = station[:, 2]
        self.bearing_std = station[:, 3]
        variances = np.square(station[:, 2:4])  # as RsuGyroEpoch.variances squares them
        self.range_variances = variances[:, 0]
        self.bearing_variances = variances[:, 1]
        self.yaw_rates = table[:, 0]
        self.times = times  # each observation's time

    @property
    def ranges(self) -> list[float]:
        """Each observation's measured range, -1 for a gyro (ranges are >= 0)."""
        return [
            -1.0 if code == 0 else measured
            for code, measured in zip(self.codes, self.observed[:, 0].tolist())
        ]

    @property
    def radii(self) -> list[float]:
        """Each observation's communication radius (a gyro's 0)."""
        radii: list[float] = self.station_table[:, 4].take(self.station_codes).tolist()
        return radii

    @property
    def rsus(self) -> list[Rsu | None]:
        """Each observation's RSU (None for a gyro)."""
        stations = self.stations
        return [stations[code] for code in self.codes]


#: The largest finite float: ``lo <= v <= _MAX`` holds for a finite ``v >= lo`` and fails for NaN and infinity.
_MAX = sys.float_info.max
#: Bearings beyond +-(pi + 1e-9) rad are refused.
_BEARING_EDGE = math.pi + 1e-9


def read_batch(
    options: Mapping[str, Any],
    last_t: float | None,
    observations: Sequence[Observation],
    environment: Environment,
) -> Batch:
    """Check the whole batch before touching the filter (every observation finite, none older than the
    session's last epoch ``last_t``, every RSU known); return its observations' stations and arrays.

    A batch that passes every check (the usual one) is read in one pass of chained comparisons, each
    refusing NaN and infinity as ``math.isfinite`` does; at the first observation that fails one, the
    batch is read again by ``_checked_batch``, which lists every problem with its field and reason."""
    stations: list[Rsu | None] = [None]  # see Batch
    station_rows = [0.0] * 5
    known: dict[str, int] = {}  # each RSU id's station
    codes: list[int] = []
    rows: list[float] = []  # two numbers per observation, see Batch
    times: list[float] = []
    default_range, default_bearing = options["range_std"], options["bearing_std"]
    default_radius = options["comm_radius"]
    earliest = -_MAX if last_t is None else last_t
    for observation in observations:
        t = observation.t
        if not earliest <= t <= _MAX:
            return _checked_batch(options, last_t, observations, environment)
        times.append(t)
        if type(observation) is RsuObservation:
            measured, bearing = observation.range, observation.bearing
            if not 0.0 <= measured <= _MAX or not -_BEARING_EDGE <= bearing <= _BEARING_EDGE:
                return _checked_batch(options, last_t, observations, environment)
            code = known.get(observation.rsu_id)
            if code is None:
                rsu = environment.rsu(observation.rsu_id)
                if rsu is None:
                    return _checked_batch(options, last_t, observations, environment)
                code = known[observation.rsu_id] = len(stations)
                stations.append(rsu)
                station_rows += (
                    rsu.x,
                    rsu.y,
                    rsu.range_std or default_range,
                    rsu.bearing_std or default_bearing,
                    rsu.radius or default_radius,
                )
            rows += (measured, bearing)
        elif type(observation) is GyroObservation:
            yaw_rate = observation.yaw_rate
            if not -_MAX <= yaw_rate <= _MAX:
                return _checked_batch(options, last_t, observations, environment)
            code = 0
            rows += (yaw_rate, 0.0)
        else:  # another type (or a subclass): the checked reading decides
            return _checked_batch(options, last_t, observations, environment)
        codes.append(code)
    return Batch(stations, station_rows, codes, rows, times)


def _checked_batch(
    options: Mapping[str, Any],
    last_t: float | None,
    observations: Sequence[Observation],
    environment: Environment,
) -> Batch:
    """``read_batch`` observation by observation, collecting every problem: raises
    ``PipelineInputError`` with all of them, or returns the batch when there are none."""
    problems = []
    stations: list[Rsu | None] = [None]  # see Batch: here a station per RSU observation
    station_rows = [0.0] * 5
    codes: list[int] = []
    rows: list[float] = []
    times: list[float] = []
    default_range, default_bearing = options["range_std"], options["bearing_std"]
    default_radius = options["comm_radius"]
    for index, observation in enumerate(observations):
        if not math.isfinite(observation.t):
            problems.append(Problem(index, "t", "must be finite"))
        elif last_t is not None and observation.t < last_t:
            problems.append(
                Problem(index, "t", f"{observation.t!r} is older than the session's last epoch t={last_t!r}")
            )
        if isinstance(observation, RsuObservation):
            rsu = environment.rsu(observation.rsu_id)
            if rsu is None:
                problems.append(Problem(index, "rsu_id", f"unknown RSU {observation.rsu_id!r}"))
            else:
                codes.append(len(stations))
                stations.append(rsu)
                station_rows.extend(
                    (
                        rsu.x,
                        rsu.y,
                        rsu.range_std or default_range,
                        rsu.bearing_std or default_bearing,
                        rsu.radius or default_radius,
                    )
                )
                times.append(observation.t)
                rows.extend((observation.range, observation.bearing))
            if not (math.isfinite(observation.range) and observation.range >= 0.0):
                problems.append(Problem(index, "range", "must be a finite distance >= 0 m"))
            if not (math.isfinite(observation.bearing) and abs(observation.bearing) <= math.pi + 1e-9):
                problems.append(Problem(index, "bearing", "must be a finite angle in [-pi, pi] rad"))
        elif isinstance(observation, GyroObservation):
            if not math.isfinite(observation.yaw_rate):
                problems.append(Problem(index, "yaw_rate", "must be finite"))
            codes.append(0)
            times.append(observation.t)
            rows.extend((observation.yaw_rate, 0.0))
        else:
            problems.append(
                Problem(index, "type", f"{observation.kind!r} is not used by the rsu_imu pipeline")
            )
    if problems:
        raise PipelineInputError(problems)
    return Batch(stations, station_rows, codes, rows, times)


def epoch_parts(
    epoch: list[int], batch: Batch, options: Mapping[str, Any], uses: dict[int, MeasurementUse]
) -> tuple[list[int], list[int]]:
    """The epoch's RSU observations inside their radius, nearest ``max_rsus`` by measured range (the
    rest recorded in ``uses`` as not used), and its gyro observations."""
    ranges, radii = batch.ranges, batch.radii
    in_radius: list[int] = []
    gyros: list[int] = []
    for i in epoch:
        measured = ranges[i]
        if measured < 0.0:  # a gyro: read_batch refused negative ranges
            gyros.append(i)
        elif measured > radii[i]:
            uses[i] = MeasurementUse(i, "rsu", False, f"range beyond the {radii[i]:g} m communication radius")
        else:
            in_radius.append(i)
    limit = options["max_rsus"]
    if len(in_radius) > 1:
        in_radius.sort(key=ranges.__getitem__)
        for i in in_radius[limit:]:
            uses[i] = MeasurementUse(i, "rsu", False, f"not among the nearest {limit} RSUs")
    return in_radius[:limit], gyros


def epoch_measurements(
    candidates: list[int], gyros: list[int], batch: Batch, options: Mapping[str, Any]
) -> RsuGyroEpoch:
    """The chosen RSU pairs and gyro readings as plain arrays, with their noise and the RSU handling."""
    rows = np.array(candidates, dtype=np.intp)  # take(): about half the time of fancy indexing
    return new_epoch(  # RsuGyroEpoch(...) without its frozen __init__, the variances taken too
        batch.positions.take(rows, 0),
        batch.observed.take(rows, 0),
        batch.range_std.take(rows),
        batch.bearing_std.take(rows),
        batch.yaw_rates.take(np.array(gyros, dtype=np.intp)),
        options["gyro_std"],
        options["rsu_handling"] == "average",
        batch.range_variances.take(rows),
        batch.bearing_variances.take(rows),
    )


class EpochRows:
    """The measurement rows of every epoch of a batch, epoch after epoch (each epoch's RSU pairs and gyro
    readings contiguous): what ``EpochParts.measured`` slices, and what a run of epochs hands the
    compiled kernels in one call (``pipelines.rsu_imu_run``); with the options' gyro noise and RSU
    handling, which every epoch's measurements share, the station of each RSU pair (``stations``:
    its index in ``station_list``, the batch's stations; a run reads the RSUs' ids through them, a few
    stations instead of a row each), and where each epoch's RSU pairs and gyro readings start
    (``starts``, ``gyro_starts``: int64, an epoch's rows end where the next one's start, the last
    epoch's at the last bound), which a run's kernel takes as they are. ``indices`` and
    ``gyro_indices`` are the observations of the rows (int64)."""

    __slots__ = (
        "averaged",
        "bearing_std",
        "bearing_variances",
        "gyro_indices",
        "gyro_starts",
        "gyro_std",
        "indices",
        "observed",
        "positions",
        "range_std",
        "range_variances",
        "starts",
        "station_list",
        "stations",
        "yaw_rates",
    )

    def __init__(
        self,
        batch: Batch,
        rows: np.ndarray,
        gyro_rows: np.ndarray,
        starts: np.ndarray,
        gyro_starts: np.ndarray,
        options: Mapping[str, Any],
    ) -> None:
        self.indices, self.gyro_indices = rows, gyro_rows
        self.positions, self.observed = batch.positions.take(rows, 0), batch.observed.take(rows, 0)
        self.range_std, self.bearing_std = batch.range_std.take(rows), batch.bearing_std.take(rows)
        self.range_variances = batch.range_variances.take(rows)
        self.bearing_variances = batch.bearing_variances.take(rows)
        self.yaw_rates = batch.yaw_rates.take(gyro_rows)
        self.gyro_std: float = options["gyro_std"]
        self.averaged: bool = options["rsu_handling"] == "average"
        self.stations = batch.station_codes.take(rows)
        self.station_list = batch.stations
        self.starts = starts
        self.gyro_starts = gyro_starts


class EpochParts:
    """One epoch of a batch as the pipeline's step takes it: its observations (indices into the batch),
    the RSUs in view it uses (nearest first) and its gyros, the records of the RSUs it leaves out
    (``epoch_parts``; the step adds its own), and where its measurements are in the batch's ``rows``
    (from ``start`` and ``gyro_start``): ``measured`` slices them when first read."""

    __slots__ = ("_measured", "candidates", "gyro_start", "gyros", "indices", "rows", "start", "uses")

    def __init__(
        self,
        indices: list[int],
        candidates: list[int],
        gyros: list[int],
        uses: dict[int, MeasurementUse],
        rows: EpochRows,
        start: int,
        gyro_start: int,
    ) -> None:
        self.indices = indices
        self.candidates = candidates
        self.gyros = gyros
        self.uses = uses
        self.rows = rows
        self.start = start
        self.gyro_start = gyro_start
        self._measured: RsuGyroEpoch | None = None

    @property
    def measured(self) -> RsuGyroEpoch:
        """The measurement arrays of the RSUs and gyros the epoch uses (slices of the batch's rows)."""
        if self._measured is None:
            rows, start, gyro_start = self.rows, self.start, self.gyro_start
            end = start + len(self.candidates)
            self._measured = new_epoch(
                rows.positions[start:end],
                rows.observed[start:end],
                rows.range_std[start:end],
                rows.bearing_std[start:end],
                rows.yaw_rates[gyro_start : gyro_start + len(self.gyros)],
                rows.gyro_std,
                rows.averaged,
                rows.range_variances[start:end],
                rows.bearing_variances[start:end],
            )
        return self._measured


class BatchEpochs:
    """A batch's epochs in time order as flat lists and arrays, with no object per epoch: each epoch's
    time (``times``), its observations (``order[bounds[k] : bounds[k + 1]]``: the batch's indices in time
    order, an epoch's ascending), its RSUs in use, nearest first, and its gyros (the rows of ``rows``
    from ``starts[k]`` and ``gyro_starts[k]``), the records of the RSUs left out (``uses``, by index)
    and per position of ``order`` the slot of a used observation's record (``slots``: see
    ``kernels_grouping.group_epochs``; -1 for any other), from which a run of epochs
    (``pipelines.rsu_imu_run``) takes its fixes' records. ``part(k)`` is epoch ``k`` as the per-epoch
    step takes it."""

    __slots__ = ("bounds", "gyro_starts", "order", "rows", "slots", "starts", "times", "uses")

    def __init__(
        self,
        times: list[float],
        order: list[int],
        bounds: list[int],
        rows: EpochRows,
        uses: dict[int, MeasurementUse],
        slots: np.ndarray,
    ) -> None:
        self.times, self.order, self.bounds, self.rows = times, order, bounds, rows
        self.starts: list[int] = rows.starts.tolist()
        self.gyro_starts: list[int] = rows.gyro_starts.tolist()
        self.uses, self.slots = uses, slots

    def __len__(self) -> int:
        return len(self.times)

    def part(self, k: int) -> EpochParts:
        """Epoch ``k`` with its own lists and the records of its RSUs left out."""
        indices = self.order[self.bounds[k] : self.bounds[k + 1]]
        start, end = self.starts[k], self.starts[k + 1]
        gyro_start, gyro_end = self.gyro_starts[k], self.gyro_starts[k + 1]
        uses = self.uses
        return EpochParts(
            indices,
            self.rows.indices[start:end].tolist(),
            self.rows.gyro_indices[gyro_start:gyro_end].tolist(),
            {i: uses[i] for i in indices if i in uses} if uses else {},
            self.rows,
            start,
            gyro_start,
        )


def batch_epochs(
    observations: Sequence[Observation], batch: Batch, options: Mapping[str, Any]
) -> BatchEpochs:
    """The batch's epochs in time order: in one compiled call (``kernels_grouping.group_epochs``), or
    with the compiled kernels off by ``reference_epochs``, which gives the same lists and arrays."""
    if not compiled_enabled():
        return reference_epochs(observations, batch, options)
    times = batch.times
    order, bounds, rows, starts, gyro_rows, gyro_starts, status, slots = group_epochs(
        np.array(times),
        batch.observed,
        batch.station_table,
        batch.station_codes,
        options["max_rsus"],
        USED_KEPT,
    )
    order_list: list[int] = order.tolist()
    bound_list: list[int] = bounds.tolist()
    uses: dict[int, MeasurementUse] = {}
    if rows.shape[0] + gyro_rows.shape[0] < len(times):  # an RSU left out: its record
        radii, limit = batch.station_table[:, 4].tolist(), options["max_rsus"]
        for i in np.flatnonzero(status >= BEYOND_RADIUS).tolist():
            uses[i] = _left_out(i, status[i] == BEYOND_RADIUS, radii[batch.codes[i]], limit)
    return BatchEpochs(
        [times[order_list[b]] for b in bound_list[:-1]],
        order_list,
        bound_list,
        EpochRows(batch, rows, gyro_rows, starts, gyro_starts, options),
        uses,
        slots,
    )


def _left_out(index: int, beyond: bool, radius: float, limit: int) -> MeasurementUse:
    """The record of an RSU observation an epoch leaves out (as ``epoch_parts`` writes it)."""
    if beyond:
        return MeasurementUse(index, "rsu", False, f"range beyond the {radius:g} m communication radius")
    return MeasurementUse(index, "rsu", False, f"not among the nearest {limit} RSUs")


def reference_epochs(
    observations: Sequence[Observation], batch: Batch, options: Mapping[str, Any]
) -> BatchEpochs:
    """``batch_epochs`` epoch by epoch in Python (``group_by_time``, ``epoch_parts``): the readable
    reference the tests hold the compiled grouping to."""
    order: list[int] = []
    bounds: list[int] = []
    rows: list[int] = []
    gyro_rows: list[int] = []
    starts: list[int] = []
    gyro_starts: list[int] = []
    uses: dict[int, MeasurementUse] = {}
    for epoch in group_by_time(observations):
        bounds.append(len(order))
        starts.append(len(rows))
        gyro_starts.append(len(gyro_rows))
        candidates, gyros = epoch_parts(epoch, batch, options, uses)
        order += epoch
        rows += candidates
        gyro_rows += gyros
    bounds.append(len(order))
    starts.append(len(rows))
    gyro_starts.append(len(gyro_rows))
    kind = {i: USED_RSU for i in rows} | {i: GYRO for i in gyro_rows}
    slots = [kind[i] * USED_KEPT + i if i in kind and i < USED_KEPT else -1 for i in order]
    return BatchEpochs(
        [batch.times[order[b]] for b in bounds[:-1]],
        order,
        bounds,
        EpochRows(
            batch,
            np.array(rows, dtype=np.int64),
            np.array(gyro_rows, dtype=np.int64),
            np.array(starts, dtype=np.int64),
            np.array(gyro_starts, dtype=np.int64),
            options,
        ),
        uses,
        np.array(slots, dtype=np.int64),
    )
