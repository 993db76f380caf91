"""A batch of ``rsu_imu`` observations as its epochs read them: checked once (``read_batch``), its rows as
arrays (``Batch``), and per epoch the RSUs in view and the gyros (``epoch_parts``) and their measurement
arrays (``epoch_measurements``); ``batch_epochs`` gives every epoch's at once, as flat lists and arrays
(``BatchEpochs``) from one compiled call (``core.kernels_grouping``), with ``reference_epochs`` the
readable reference. Reading the batch once makes an epoch's arrays a few index operations instead of
arrays built from Python lists; grouping it in one call makes no Python object per epoch (a 20-epoch
batch: about 1.2 us an epoch less than grouping, selecting and listing epoch by epoch, docs/benchmarks.md)."""

from __future__ import annotations

import itertools
import math
import struct
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.kernels_grouping import BEYOND_RADIUS, NOT_NEAREST, PAST_KEPT, group_epochs, write_records
from edgepos.core.observation_codec import flat_layout, text_field
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.core.updates import RsuGyroEpoch, new_epoch
from edgepos.pipelines.base import Environment, MeasurementUse, PipelineInputError, Problem, Rsu
from edgepos.pipelines.epochs import group_by_time

#: The most measurement indices whose records a run takes by slot (``BatchEpochs.slots``) and
#: ``rsu_imu_run.used`` keeps per kind.
USED_KEPT = 4096


class Batch:
    """A batch's observations as the epochs read them: each RSU observation's station, and per
    observation its time, its station and its two measured numbers (range and bearing, or a gyro's yaw
    rate and 0) as one row of ``table``; the stations' numbers (x, y, range and bearing standard
    deviations with the options' defaults filled in, communication radius) as rows of
    ``station_table`` (``stations[0]`` None, a gyro's, its numbers zeros). Read once per batch
    (``read_batch``): a station's numbers are listed once per batch, not once per observation.

    ``batch_epochs`` makes the rows a run takes from these two tables in one compiled call; the
    observations' own arrays below (taken per observation, ``take``) serve the per-epoch step's
    measurements after the gate or the monitor leaves one out, and the reference grouping."""

    __slots__ = ("_station", "compiled", "ids", "station_table", "stations", "table")

    def __init__(
        self,
        stations: list[Rsu | None],
        station_rows: list[float],
        values: list[float],
        ids: list[str] | None = None,
    ) -> None:
        """``ids``: the RSU ids of ``stations[1:]`` as the observations give them, when every observation
        is an ``RsuObservation`` or a ``GyroObservation`` (``batch_records`` then writes its records)."""
        self.stations, self.ids = stations, ids
        self.compiled = compiled_enabled()  # grouped and its records written by the compiled kernels
        count = len(values) // 4
        # four numbers a row (t, station, and the two measured) packed straight into the table: a
        # third of the time np.array takes to read a list of floats
        self.table = np.empty((count, 4))
        struct.pack_into(f"{4 * count}d", self.table.data, 0, *values)
        self.station_table = np.array(station_rows, dtype=float).reshape(len(stations), 5)
        self._station: np.ndarray | None = None

    @property
    def codes(self) -> list[int]:
        """Each observation's station (0: a gyro)."""
        codes: list[int] = self.table[:, 1].astype(np.intp).tolist()
        return codes

    @property
    def times(self) -> list[float]:
        """Each observation's time."""
        times: list[float] = self.table[:, 0].tolist()
        return times

    @property
    def observed(self) -> np.ndarray:
        """Each observation's two measured numbers (a view of ``table``)."""
        return self.table[:, 2:4]

    @property
    def yaw_rates(self) -> np.ndarray:
        """Each observation's first measured number, a gyro's yaw rate (a view of ``table``)."""
        return self.table[:, 2]

    @property
    def station_codes(self) -> np.ndarray:
        """``codes`` as an array: what rows of stations take."""
        return self.table[:, 1].astype(np.intp)

    def _stations(self) -> np.ndarray:
        """Each observation's station row (made when first asked)."""
        if self._station is None:
            self._station = self.station_table.take(self.station_codes, 0)
        return self._station

    @property
    def positions(self) -> np.ndarray:
        """Each observation's station position (a gyro's zeros)."""
        return self._stations()[:, 0:2]

    @property
    def range_std(self) -> np.ndarray:
        return self._stations()[:, 2]

    @property
    def bearing_std(self) -> np.ndarray:
        return self._stations()[:, 3]

    @property
    def range_variances(self) -> np.ndarray:
        """As ``RsuGyroEpoch.variances`` squares the standard deviations."""
        variances: np.ndarray = np.square(self.range_std)
        return variances

    @property
    def bearing_variances(self) -> np.ndarray:
        variances: np.ndarray = np.square(self.bearing_std)
        return variances

    @property
    def ranges(self) -> list[float]:
        """Each observation's measured range, -1 for a gyro (ranges are >= 0)."""
        return [
            -1.0 if code == 0 else measured for code, measured in zip(self.codes, self.yaw_rates.tolist())
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
    values: list[float] = []  # four numbers per observation, see Batch
    default_range, default_bearing = options["range_std"], options["bearing_std"]
    default_radius = options["comm_radius"]
    earliest = -_MAX if last_t is None else last_t
    for observation in observations:
        t = observation.t
        if not earliest <= t <= _MAX:
            return _checked_batch(options, last_t, observations, environment)
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
            values += (t, code, measured, bearing)
        elif type(observation) is GyroObservation:
            yaw_rate = observation.yaw_rate
            if not -_MAX <= yaw_rate <= _MAX:
                return _checked_batch(options, last_t, observations, environment)
            values += (t, 0, yaw_rate, 0.0)
        else:  # another type (or a subclass): the checked reading decides
            return _checked_batch(options, last_t, observations, environment)
    return Batch(stations, station_rows, values, list(known))


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
    values: list[float] = []
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
                values.extend((observation.t, len(stations), observation.range, observation.bearing))
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
            if not (math.isfinite(observation.range) and observation.range >= 0.0):
                problems.append(Problem(index, "range", "must be a finite distance >= 0 m"))
            if not (math.isfinite(observation.bearing) and abs(observation.bearing) <= math.pi + 1e-9):
                problems.append(Problem(index, "bearing", "must be a finite angle in [-pi, pi] rad"))
        elif isinstance(observation, GyroObservation):
            if not math.isfinite(observation.yaw_rate):
                problems.append(Problem(index, "yaw_rate", "must be finite"))
            values.extend((observation.t, 0, observation.yaw_rate, 0.0))
        else:
            problems.append(
                Problem(index, "type", f"{observation.kind!r} is not used by the rsu_imu pipeline")
            )
    if problems:
        raise PipelineInputError(problems)
    return Batch(stations, station_rows, values)


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
        arrays: tuple[np.ndarray, ...],
        bounds: np.ndarray,
        options: Mapping[str, Any],
    ) -> None:
        """``arrays``: ``kernels_grouping.group_epochs``'s from ``indices`` on; ``bounds``: its (3, E + 1)
        bounds (each row of a C-contiguous array: the kernels take them as they are)."""
        (
            indices,
            self.stations,
            self.positions,
            self.observed,
            self.range_std,
            self.bearing_std,
            self.range_variances,
            self.bearing_variances,
            self.yaw_rates,
        ) = arrays
        used = self.range_std.shape[0]
        self.indices, self.gyro_indices = indices[:used], indices[used:]
        self.starts, self.gyro_starts = bounds[1], bounds[2]
        self.gyro_std: float = options["gyro_std"]
        self.averaged: bool = options["rsu_handling"] == "average"
        self.station_list = batch.stations


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
    and per position of ``order`` the slot of an observation's record in a run's fix (``slots``: see
    ``kernels_grouping.group_epochs``), from which a run of epochs (``pipelines.rsu_imu_run``) takes
    its fixes' records. ``part(k)`` is epoch ``k`` as the per-epoch step takes it."""

    __slots__ = ("bounds", "gyro_starts", "order", "rows", "slots", "starts", "times", "uses")

    def __init__(
        self,
        times: list[float],
        bounds: np.ndarray,
        order_slots: np.ndarray,
        rows: EpochRows,
        uses: dict[int, MeasurementUse],
    ) -> None:
        self.times, self.rows, self.uses = times, rows, uses
        self.bounds, self.starts, self.gyro_starts = bounds.tolist()
        self.order: list[int] = order_slots[0].tolist()
        self.slots = order_slots[1]

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
    """The batch's epochs in time order and their rows: in one compiled call
    (``kernels_grouping.group_epochs``), or with the compiled kernels off by ``reference_epochs``, which
    gives the same lists and arrays."""
    if not batch.compiled:
        return reference_epochs(observations, batch, options)
    limit = options["max_rsus"]
    times, bounds, order_slots, *arrays = group_epochs(batch.table, batch.station_table, limit, USED_KEPT)
    rows = EpochRows(batch, tuple(arrays), bounds, options)
    uses: dict[int, MeasurementUse] = {}
    count = batch.table.shape[0]
    if rows.indices.shape[0] + rows.gyro_indices.shape[0] < count:  # an RSU left out: its record
        order, slots = order_slots
        radii = batch.station_table[:, 4].tolist()
        for position in np.flatnonzero(slots <= BEYOND_RADIUS).tolist():
            i = int(order[position])
            radius = radii[int(batch.table[i, 1])]
            uses[i] = _left_out(i, slots[position] == BEYOND_RADIUS, radius, limit)
    return BatchEpochs(times.tolist(), bounds, order_slots, rows, uses)


def _left_out(index: int, beyond: bool, radius: float, limit: int) -> MeasurementUse:
    """The record of an RSU observation an epoch leaves out (as ``epoch_parts`` writes it)."""
    if beyond:
        return MeasurementUse(index, "rsu", False, f"range beyond the {radius:g} m communication radius")
    return MeasurementUse(index, "rsu", False, f"not among the nearest {limit} RSUs")


def reference_epochs(
    observations: Sequence[Observation], batch: Batch, options: Mapping[str, Any]
) -> BatchEpochs:
    """``batch_epochs`` epoch by epoch in Python (``group_by_time``, ``epoch_parts``, a ``take`` of the
    batch's arrays per array): the readable reference the tests hold the compiled grouping to."""
    order: list[int] = []
    bounds: list[list[int]] = [[], [], []]
    rows: list[int] = []
    gyro_rows: list[int] = []
    uses: dict[int, MeasurementUse] = {}
    for epoch in group_by_time(observations):
        for bound, at in zip(bounds, (len(order), len(rows), len(gyro_rows)), strict=True):
            bound.append(at)
        candidates, gyros = epoch_parts(epoch, batch, options, uses)
        order += epoch
        rows += candidates
        gyro_rows += gyros
    for bound, at in zip(bounds, (len(order), len(rows), len(gyro_rows)), strict=True):
        bound.append(at)
    kind = {i: 0 for i in rows} | {i: 1 for i in gyro_rows}
    ranges, radii = batch.ranges, batch.radii
    slots = [
        (kind[i] * USED_KEPT + i if i < USED_KEPT else PAST_KEPT)
        if i in kind
        else (BEYOND_RADIUS if ranges[i] > radii[i] else NOT_NEAREST)
        for i in order
    ]
    index = np.array(rows, dtype=np.int64)
    arrays = (
        np.array(rows + gyro_rows, dtype=np.int64),
        batch.station_codes.astype(np.int64).take(index),
        batch.positions.take(index, 0),
        batch.observed.take(index, 0),
        batch.range_std.take(index),
        batch.bearing_std.take(index),
        batch.range_variances.take(index),
        batch.bearing_variances.take(index),
        batch.yaw_rates.take(np.array(gyro_rows, dtype=np.int64)),
    )
    times = batch.times
    return BatchEpochs(
        [times[order[b]] for b in bounds[0][:-1]],
        np.array(bounds, dtype=np.int64),
        np.array([order, slots], dtype=np.int64).reshape(2, len(order)),
        EpochRows(batch, arrays, np.array(bounds, dtype=np.int64), options),
        uses,
    )


def _heads() -> tuple[np.ndarray, np.ndarray] | None:
    """The name bytes of RSU and gyro records when ``core.observation_codec`` lays them out as
    ``kernels_grouping.write_records`` writes them (and the machine is little-endian); else None."""
    rsu, gyro = flat_layout(RsuObservation), flat_layout(GyroObservation)
    if sys.byteorder != "little" or rsu is None or gyro is None:
        return None
    if rsu[1:] != (("t", "range", "bearing"), ("rsu_id",)) or gyro[1:] != (("t", "yaw_rate"), ()):
        return None
    return np.frombuffer(rsu[0], np.uint8), np.frombuffer(gyro[0], np.uint8)


_HEADS = _heads()


def batch_records(batch: Batch) -> tuple[np.ndarray, list[int]] | None:
    """The lag window's records of the batch's observations (``core.observation_codec``'s bytes, which
    ``lag_state.encode_epochs`` writes from the observations), back to back in the batch's order, and
    where each observation's ends: written from the batch's table in one compiled call. None when the
    codec's encoders must write them (a batch read observation by observation, compiled kernels off)."""
    if batch.ids is None or _HEADS is None or not batch.compiled:
        return None
    ids = tuple(batch.ids)
    texts = _STATION_TEXTS.get(ids)
    if texts is None:
        texts = _station_texts(ids)
    written, ends = write_records(batch.table, *texts, *_HEADS)
    return written, ends.tolist()


#: ``_station_texts`` by the RSU ids of a batch's stations (few and the same batch after batch), up to
#: ``STATION_TEXTS_KEPT`` of them (then emptied: a new fleet's stations fill it again).
_STATION_TEXTS: dict[tuple[str, ...], tuple[np.ndarray, np.ndarray]] = {}
STATION_TEXTS_KEPT = 1024


def _station_texts(ids: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The text fields of the stations ``ids`` (``stations[1:]``) back to back, and where station
    ``code``'s starts (the gyro's station 0 has none): what ``write_records`` takes (read only)."""
    texts = [text_field(rsu_id) for rsu_id in ids]
    offsets = np.array([0, 0, *itertools.accumulate(map(len, texts))], dtype=np.int64)
    offsets.flags.writeable = False
    if len(_STATION_TEXTS) >= STATION_TEXTS_KEPT:
        _STATION_TEXTS.clear()
    written = _STATION_TEXTS[ids] = (np.frombuffer(b"".join(texts), np.uint8), offsets)
    return written
