"""Late and out-of-order measurements: a lag window around every pipeline (history replay).

Over a radio link measurements arrive late and out of order: an RSU's range comes through the RSU's
backhaul after the vehicle's own gyro samples; a retransmitted packet carries samples older than the
last batch. :class:`LagWindow` (the registry puts it around every pipeline, outside
``plausibility.Plausible``) keeps the last ``max_delay_s`` seconds of the session: the measurements
and a few *checkpoints* (the inner state at batch boundaries). A measurement older than the session's
newest epoch but inside the window is inserted at its own time and the filter runs again from the
latest checkpoint before it, through every later measurement (history replay, as robot fusion
frameworks do). Replay is exact: the inner pipelines' states carry everything a step needs, so the
result is the state filtering in time order would have reached, whatever the order of arrival (to
round-off: an epoch's measurements may be stacked in another order). An exact out-of-sequence update
exists only for linear filters with one model; the pipelines here are nonlinear banks, so replay it is
(its cost is measured by ``bench/late_measurements.py``).

Every response holds the fixes of the batch's epochs and, for epochs answered before whose estimate
the late data changed, the *revised* fixes (``Fix.revised``), all in time order: a client keeps the
last fix it received for each ``t``.

A measurement older than the window (``t < newest - max_delay_s``, or before the oldest epoch the
window still holds) is not invalid: it is reported ``used: false`` with how late it was in the
response's newest fix, and the rest of the batch is applied. It is still validated with the batch:
a malformed late measurement refuses the batch as any other would.

Bounds: ``max_delay_s`` (0..10 s), ``max_window_epochs`` (the most epochs the window keeps; when more
arrive within ``max_delay_s`` the oldest leave it), and ``max_lead_s`` (a measurement more than that
after every other of its batch is refused: a clock error that would move the session past all later
data). The service refuses at creation a window whose full replay would cost more CPU than its batch
budget (``pipelines.cost``).

State (``lag_state``): the window's options and newest epoch, a few checkpoints (the inner state at
batch boundaries, the first one the window's *base*), the current inner state, and the window's epochs
as records. The current state is the base state filtered through every epoch of the window. A batch in
time order (the usual one) is applied on the window's bytes (``LagWindow._in_order``, ``lag_state._spans``):
its new records and checkpoint are appended and the pruned ones cut off without decoding or copying the
stored ones one by one (the new records as the inner pipeline wrote them from its arrays when it offers
``written_records``, the same bytes); every other batch goes through the decoded window.
"""

from __future__ import annotations

import bisect
import dataclasses
import itertools
import math
from collections.abc import Mapping, Sequence
from typing import Any

from edgepos.core.observations import Observation
from edgepos.pipelines.base import (
    Environment,
    Fix,
    InitialState,
    MeasurementUse,
    OptionSpec,
    PipelineInputError,
    Problem,
    StateSummary,
)
from edgepos.pipelines.lag_state import (  # noqa: F401  # re-exported: tests and benches read states through lag
    MAGIC,
    VERSION,
    _Checkpoint,
    _pack,
    _pack_parts,
    _spans,
    _unpack,
    _Window,
    decode_epoch,
    encode_epoch,
    encode_epochs,
    newest_epoch,
)
from edgepos.pipelines.wrapping import WrappingPipeline

_INF = math.inf

IN_ORDER_PATH = True
"""Whether a batch in time order takes ``LagWindow._in_order`` (the tests switch it off to compare)."""

CHECKPOINTS_PER_WINDOW = 8
"""A new checkpoint is kept only when it is at least ``max_delay_s / CHECKPOINTS_PER_WINDOW`` after the
previous one: at most about this many states per window, whatever the batch rate (a state is 2.4 kB for
rsu_imu), at the price of replaying up to that much more than strictly needed."""

OPTION_SPECS: tuple[OptionSpec, ...] = (
    OptionSpec(
        "max_delay_s",
        "number",
        1.0,
        "Lag window (s): a measurement up to this much older than the session's newest epoch is inserted at "
        "its own time and the filter runs again from there (earlier fixes come back revised); an older one is "
        "reported used=false. 0 keeps no window.",
        0.0,
        10.0,
    ),
    OptionSpec(
        "max_window_epochs",
        "integer",
        200,
        "The most epochs the lag window keeps; when more arrive within max_delay_s the oldest leave it "
        "(10 s at 20 Hz). Bounded so that replaying the whole window fits the server's CPU budget per batch.",
        1,
        1000,
    ),
    OptionSpec(
        "max_lead_s",
        "number",
        10.0,
        "A measurement more than this (s) after every other measurement of its batch is refused (422): a "
        "clock error that would put the session's newest epoch past all later data. At least the longest "
        "gap between a batch's epochs.",
        1.0,
        3600.0,
    ),
)
DEFAULTS: dict[str, Any] = {spec.name: spec.default for spec in OPTION_SPECS}


def _own(options: Mapping[str, Any]) -> dict[str, Any]:
    return {name: options.get(name, default) for name, default in DEFAULTS.items()}


def _finite(t: Any) -> bool:
    if type(t) is float:  # the usual case, checked first: a few calls per observation of every batch
        return -math.inf < t < math.inf
    return isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t)


@dataclasses.dataclass(frozen=True)
class _Arrival:
    """A batch sorted out against the window: indices into the batch."""

    fresh: list[int]  # newer than the newest epoch (or malformed times: the inner pipeline refuses them)
    late: list[int]  # at or before the newest epoch, inside the window
    too_late: list[int]  # before the window


class LagWindow(WrappingPipeline):
    """``inner`` with a lag window for late measurements and revised fixes (see the module docstring)."""

    own_specs = OPTION_SPECS

    # -- sessions ----------------------------------------------------------------------------------
    def create(self, options: Mapping[str, Any], initial: InitialState | None) -> bytes:
        inner_state = self.inner.create(self.inner_options(options), initial)
        return _pack(_Window(_own(options), None, [_Checkpoint(None, inner_state)], inner_state, [], []))

    def summarise(self, state: bytes) -> StateSummary:
        window = _unpack(state)
        summary = self.inner.summarise(window.current)
        return dataclasses.replace(summary, options={**summary.options, **window.options})

    def replayed_observations(
        self, state: bytes, observations: Sequence[Observation] | None
    ) -> list[Observation]:
        """The stored observations that applying ``observations`` would filter again (none for a batch in
        time order), or with None every observation of the window: what the caller must look up
        (RSUs, neighbours) and budget for beyond the batch itself."""
        if observations is not None and _all_after_newest(state, observations):
            return []  # the usual batch, in time order: only the header is read
        window = _unpack(state)
        if observations is None:
            return window.observations()
        arrival = _sort_out(window, observations)
        if arrival.late:
            earliest = min(observations[i].t for i in arrival.late)
            return window.observations(_replay_start(window, earliest)[1])
        if arrival.too_late and not arrival.fresh and window.newest is not None:
            return window.observations(_replay_start(window, window.newest)[1])  # see _newest_fix
        return []

    # -- batches -----------------------------------------------------------------------------------
    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        if IN_ORDER_PATH:
            done = self._in_order(state, observations, environment)
            if done is not None:
                return done
        window = _unpack(state)
        _check_lead(window, observations)
        arrival = _sort_out(window, observations)
        # Every problem of the batch in one answer: the too-late measurements' own, then the rest's.
        problems = self._too_late_problems(window, observations, arrival.too_late, environment)
        uses = _too_late_uses(window, observations, arrival.too_late)  # judged by the window before the batch
        try:
            if arrival.late:
                fixes = self._replay(window, observations, arrival, environment)
            elif arrival.fresh:
                fixes = self._append(window, observations, arrival.fresh, environment)
            else:
                fixes = []
        except PipelineInputError as error:
            raise PipelineInputError([*problems, *error.problems]) from None
        if problems:
            raise PipelineInputError(problems)
        if uses:
            fixes = self._report_too_late(window, uses, fixes, environment)
        _prune(window)
        return fixes, _pack(window)

    def _in_order(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes] | None:
        """The usual batch, every observation newer than the window's newest epoch and in time order, with
        no more epochs than the window keeps: what ``_append`` and ``_prune`` do, on the window's bytes
        (``_spans``) without decoding or copying its checkpoints and records one by one. None for any
        other batch or state (no newest epoch yet, an older version, a problem to report): the general
        path takes it, and gives the same bytes and fixes where both apply (tests/pipelines/test_lag.py)."""
        spans = _spans(state)
        if spans is None or spans.newest is None or not observations:
            return None
        delay, limit, lead = spans.options
        previous = spans.newest
        times: list[float] = []
        counts: list[int] = []  # each epoch's observations
        for observation in observations:
            t = observation.t
            if not (type(t) is float and -_INF < t < _INF) and not _finite(t):  # _finite's test, inline first
                return None
            if t > previous:
                times.append(t)
                counts.append(1)
                previous = t
            elif t == previous and counts:
                counts[-1] += 1
            else:
                return None  # late, or out of order within the batch
        if len(times) > limit or (len(times) > 1 and times[-1] - times[-2] > lead):
            return None
        fixes, current = self.inner.process(bytes(spans.current), observations, environment)
        newest = spans.newest
        checkpoint_times = spans.checkpoint_times
        checkpoint_states: list[bytes | memoryview] = list(spans.checkpoint_states)
        last = checkpoint_times[-1]
        if last is None or newest - last >= delay / CHECKPOINTS_PER_WINDOW:  # as _maybe_checkpoint
            checkpoint_times = [*checkpoint_times, newest]
            checkpoint_states.append(spans.current)
        pieces, record_ends = self._records(observations, counts)
        all_times = spans.times + times
        keep, start = _pruning(times[-1], delay, limit, checkpoint_times, all_times)
        if keep is None:
            packed = _pack_parts(spans.options, times[-1], [(times[-1], current)], current, [], [], [])
            return fixes, packed
        ends = spans.ends
        offset = ends[start - 1] if start else 0
        stored_end = ends[-1] if ends else 0
        kept_ends = [end - offset for end in ends[start:]]
        end = stored_end - offset
        kept_ends += [end + record_end for record_end in record_ends]
        packed = _pack_parts(
            spans.options,
            times[-1],
            list(zip(checkpoint_times[keep:], checkpoint_states[keep:], strict=True)),
            current,
            all_times[start:],
            kept_ends,
            [spans.records[offset:stored_end], *pieces],
        )
        return fixes, packed

    def _records(
        self, observations: Sequence[Observation], counts: list[int]
    ) -> tuple[list[bytes | memoryview], list[int]]:
        """The records of a batch in time order whose epochs hold ``counts`` observations each, as pieces
        of bytes and where each epoch's record ends in them: as the inner pipeline wrote them from its
        arrays (``written_records``, the same bytes), or else by ``encode_epochs``."""
        writer = getattr(self.inner, "written_records", None)
        written = None if writer is None else writer(observations)
        if written is None:
            records = encode_epochs(observations, counts)
            return list(records), list(itertools.accumulate(map(len, records)))
        data, observation_ends = written
        record_ends = []
        last = -1
        for count in counts:
            last += count
            record_ends.append(observation_ends[last])
        return [memoryview(data)], record_ends

    def _append(
        self, window: _Window, observations: Sequence[Observation], fresh: list[int], environment: Environment
    ) -> list[Fix]:
        """A batch newer than the window: filtered from the current state; the state before it may
        become a checkpoint."""
        order = sorted(fresh, key=lambda i: observations[i].t)
        times = sorted({observations[i].t for i in order if _finite(observations[i].t)})
        limit = window.options["max_window_epochs"]
        if len(times) > limit:
            # More epochs than the window keeps: the state before its last ``limit`` epochs becomes a
            # checkpoint, so that late data for them (and the newest fix) can still be filtered again.
            split = times[-limit - 1]
            head = [i for i in order if not observations[i].t > split]
            order = [i for i in order if observations[i].t > split]
            try:
                fixes = self._append(window, observations, head, environment)
            except PipelineInputError as error:
                rest = self._problems_alone(window, [(i, observations[i]) for i in order], environment)
                raise PipelineInputError([*error.problems, *rest]) from None
            return fixes + self._append(window, observations, order, environment)
        fixes, new_state = self._filter(window.current, [(i, observations[i]) for i in order], environment)
        _maybe_checkpoint(window, window.newest, window.current)
        window.current = new_state
        _extend(window, [observations[i] for i in order])
        return fixes

    def _replay(
        self,
        window: _Window,
        observations: Sequence[Observation],
        arrival: _Arrival,
        environment: Environment,
    ) -> list[Fix]:
        """Late measurements: filter again from the latest checkpoint before the earliest of them, through
        the window's later observations and the batch, segment by segment between the checkpoints (so the
        checkpoints stay valid), and answer the changed epochs as revised fixes."""
        earliest = min(observations[i].t for i in arrival.late)
        checkpoint_index, start = _replay_start(window, earliest)
        answered = set(window.times)
        # The epochs from the checkpoint on: stored ones (their records kept unless late data joins
        # them), then the batch's. Within an epoch stored observations come first, then the batch's in
        # its order; index -1 marks a stored observation (it has no index in this batch).
        arriving: dict[float, list[int]] = {}
        for i in sorted((*arrival.late, *arrival.fresh), key=lambda i: observations[i].t):
            arriving.setdefault(observations[i].t, []).append(i)
        epochs: dict[float, tuple[list[tuple[int, Observation]], bytes | None]] = {}
        for t, record in zip(window.times[start:], window.records[start:], strict=True):
            epochs[t] = ([(-1, o) for o in decode_epoch(record)], record)
        for t, indices in arriving.items():
            stored, _ = epochs.get(t, ([], None))
            epochs[t] = (stored + [(i, observations[i]) for i in indices], None)
        times = sorted(epochs)
        bounds = [c.t for c in window.checkpoints[checkpoint_index + 1 :]]
        if window.newest is not None and arrival.fresh:
            bounds.append(window.newest)  # the state before the batch's new epochs may become a checkpoint
        state = window.checkpoints[checkpoint_index].state
        fixes: list[Fix] = []
        segment_start = 0
        replaced: list[bytes] = []
        problems: list[Problem] = []
        for bound in [*bounds, None]:
            end = len(times) if bound is None else bisect.bisect_right(times, bound)
            part = [item for t in times[segment_start:end] for item in epochs[t][0]]
            if part and problems:
                problems += self._problems_alone(
                    window, part, environment
                )  # the rest only to list its problems
            elif part:
                try:
                    new, state = self._filter(state, part, environment)
                except PipelineInputError as error:
                    problems += error.problems
                else:
                    fixes += new
            if bound is not None:
                replaced.append(state)
            segment_start = end
        if problems:
            raise PipelineInputError(problems)
        # The checkpoints after the replayed one now hold the late data; the state at the old newest
        # epoch is offered as a checkpoint like any batch boundary.
        for checkpoint, new_state in zip(window.checkpoints[checkpoint_index + 1 :], replaced, strict=False):
            checkpoint.state = new_state
        if arrival.fresh and window.newest is not None:
            _maybe_checkpoint(window, window.newest, replaced[-1])
        window.current = state
        window.times = window.times[:start] + times
        window.records = window.records[:start] + [
            record if record is not None else encode_epoch([o for _, o in items])
            for items, record in (epochs[t] for t in times)
        ]
        window.newest = times[-1] if window.newest is None else max(window.newest, times[-1])
        return [
            dataclasses.replace(fix, revised=True) if fix.t in answered else fix
            for fix in fixes
            if fix.t >= earliest or fix.t not in answered
        ]

    def _filter(
        self, state: bytes, items: Sequence[tuple[int, Observation]], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        """The inner pipeline on ``items`` (batch index, observation; index -1: stored), with the fixes'
        measurement uses and the problems it finds numbered as the batch's."""
        indices = [i for i, _ in items]
        try:
            fixes, state = self.inner.process(state, [o for _, o in items], environment)
        except PipelineInputError as error:
            raise PipelineInputError(
                [_renumbered_problem(p, indices, items) for p in error.problems]
            ) from None
        if indices == list(range(len(indices))):
            return fixes, state  # the whole batch in its own order: already numbered as the batch's
        return [_renumbered(fix, indices) for fix in fixes], state

    def _too_late_problems(
        self,
        window: _Window,
        observations: Sequence[Observation],
        indices: list[int],
        environment: Environment,
    ) -> list[Problem]:
        """Too-late measurements are not filtered, but a malformed one still refuses the batch: they are
        checked by the inner pipeline on a fresh session of the same options (which has no clock to be
        older than)."""
        if not indices:
            return []
        order = sorted(indices, key=lambda i: observations[i].t)
        return self._problems_alone(window, [(i, observations[i]) for i in order], environment)

    def _problems_alone(
        self, window: _Window, items: Sequence[tuple[int, Observation]], environment: Environment
    ) -> list[Problem]:
        """What the inner pipeline finds wrong with ``items`` (in time order) on a fresh session of the same
        options: the problems of measurements that are not filtered from the session's state (too late, or
        after a part of the batch that was refused already)."""
        options = self.inner.summarise(window.current).options
        fresh = self.inner.create(self.inner_options(options), None)
        try:
            self._filter(fresh, items, environment)
        except PipelineInputError as error:
            return error.problems
        return []

    def _report_too_late(
        self, window: _Window, uses: list[MeasurementUse], fixes: list[Fix], environment: Environment
    ) -> list[Fix]:
        """The too-late measurements as used=false in the response's newest fix; a batch with nothing else
        gets the session's newest fix again (computed anew from its checkpoint, marked revised)."""
        if not fixes:
            fixes = self._newest_fix(window, environment)
            if not fixes:
                return fixes
        last = fixes[-1]
        fixes[-1] = dataclasses.replace(
            last, measurements=sorted([*last.measurements, *uses], key=lambda u: u.index)
        )
        return fixes

    def _newest_fix(self, window: _Window, environment: Environment) -> list[Fix]:
        if window.newest is None or not window.records:
            return []
        index, start = _replay_start(window, window.newest)
        fixes, _ = self.inner.process(
            window.checkpoints[index].state, window.observations(start), environment
        )
        return [dataclasses.replace(fixes[-1], measurements=[], revised=True)] if fixes else []

    def smooth(
        self,
        state: bytes,
        observations: Sequence[Observation],
        environment: Environment,
        lag_s: float | None = None,
    ) -> list[Fix]:
        """The inner pipeline's smoother from the session's current state (evaluation runs it over a
        whole run; the track endpoint over the window, through :meth:`track`)."""
        return self.inner.smooth(_unpack(state).current, observations, environment, lag_s)

    # -- the window's track ------------------------------------------------------------------------
    def track(self, state: bytes, environment: Environment, smoothed: bool) -> list[Fix]:
        """The window's estimates, one per epoch in time order: filtered again from the window's base with
        the environment as it is now, or (``smoothed``) smoothed over the whole window by the pipeline's
        smoother. ValueError when smoothing is asked of a pipeline that has none."""
        window = _unpack(state)
        observations = window.observations()
        if not observations:
            return []
        if smoothed:
            if not self.smoother:
                raise ValueError(f"the {self.name} pipeline has no smoother")
            fixes = self.inner.smooth(window.base.state, observations, environment)
        else:
            fixes, _ = self.inner.process(window.base.state, observations, environment)
        return [dataclasses.replace(fix, measurements=[]) for fix in fixes]

    def window_bounds(self, state: bytes) -> tuple[float | None, float | None, dict[str, Any]]:
        """The window's oldest and newest epoch times (None: empty) and its options."""
        window = _unpack(state)
        return (window.times[0] if window.times else None), window.newest, window.options


# -- sorting a batch out -----------------------------------------------------------------------------
def _all_after_newest(state: bytes, observations: Sequence[Observation]) -> bool:
    """Whether every observation is newer than the window's newest epoch (False when unsure: no newest
    epoch yet, a malformed time or a state that does not read), from the state's header alone."""
    newest = newest_epoch(state)
    if newest is None:
        return False
    for observation in observations:
        t = observation.t
        if not (_finite(t) and t > newest):
            return False
    return True


def _sort_out(window: _Window, observations: Sequence[Observation]) -> _Arrival:
    newest = window.newest
    if newest is None:
        return _Arrival(list(range(len(observations))), [], [])
    delay = window.options["max_delay_s"]
    floor = newest - delay
    base = window.base.t
    fresh, late, too_late = [], [], []
    for index, observation in enumerate(observations):
        t = observation.t
        if not _finite(t) or t > newest:
            fresh.append(index)  # a malformed time goes to the inner pipeline, which names it
        elif t < floor or (base is not None and t <= base) or delay == 0:
            too_late.append(index)
        else:
            late.append(index)
    return _Arrival(fresh, late, too_late)


def _too_late_uses(
    window: _Window, observations: Sequence[Observation], indices: list[int]
) -> list[MeasurementUse]:
    """The report of each too-late measurement: how late against the session's newest epoch before the
    batch, and which bound it missed."""
    newest, delay = window.newest, window.options["max_delay_s"]
    uses = []
    for i in indices:
        observation = observations[i]
        assert newest is not None  # nothing is too late before the first epoch
        lateness = newest - observation.t
        if lateness > delay or delay == 0:
            why = f"beyond the lag window (max_delay_s {delay:g} s)"
        elif not window.times:  # more epochs since the last checkpoint than max_window_epochs: none kept
            why = f"the lag window holds no epoch before it (max_window_epochs {window.options['max_window_epochs']})"
        else:
            why = (
                f"before the oldest epoch the lag window still holds (t={window.times[0]!r}; max_window_epochs "
                f"{window.options['max_window_epochs']})"
            )
        reason = (
            f"too late: t={observation.t!r} is {lateness:.6g} s older than the session's newest epoch "
            f"t={newest!r}, {why}; not used, the rest of the batch was applied"
        )
        doppler = getattr(observation, "doppler_hz", None) is not None
        uses.append(
            MeasurementUse(
                i, observation.kind, False, reason, False if doppler else None, reason if doppler else None
            )
        )
    return uses


def _check_lead(window: _Window, observations: Sequence[Observation]) -> None:
    """Refuse measurements more than max_lead_s after every other measurement of the batch."""
    times = sorted({o.t for o in observations if _finite(o.t)})
    if len(times) < 2:
        return
    bound = window.options["max_lead_s"]
    if times[-1] - times[-2] <= bound:
        return
    problems = [
        Problem(
            index,
            "t",
            (
                f"{o.t!r} is {o.t - times[-2]:.6g} s after every other measurement of the batch (latest other "
                f"t={times[-2]!r}), more than max_lead_s {bound:g} s: a clock error? It would make the others too late"
            ),
        )
        for index, o in enumerate(observations)
        if o.t == times[-1]
    ]
    raise PipelineInputError(problems)


def _replay_start(window: _Window, earliest: float) -> tuple[int, int]:
    """The latest checkpoint whose state is from before ``earliest``, and the index of the first window
    observation after that checkpoint."""
    index = 0
    for i, checkpoint in enumerate(window.checkpoints):
        if checkpoint.t is None or checkpoint.t < earliest:
            index = i
    t = window.checkpoints[index].t
    start = 0 if t is None else bisect.bisect_right(window.times, t)
    return index, start


def _renumbered(fix: Fix, indices: Sequence[int]) -> Fix:
    """A fix of a sub-list with its measurement indices mapped back to the batch's; uses of stored
    observations (index -1: they belong to an earlier batch) are left out."""
    uses = []
    changed = False
    for use in fix.measurements:
        index = indices[use.index]
        if index == use.index:
            uses.append(use)
            continue
        changed = True
        if index >= 0:
            uses.append(dataclasses.replace(use, index=index))
    return dataclasses.replace(fix, measurements=uses) if changed else fix


def _renumbered_problem(
    problem: Problem, indices: Sequence[int], items: Sequence[tuple[int, Observation]]
) -> Problem:
    """A problem of a sub-list numbered as the batch's. A stored observation (applied by an earlier batch)
    refused now (its RSU left the registry, say) is named by its time, without an index."""
    if problem.index is None or not 0 <= problem.index < len(indices):
        return problem
    index = indices[problem.index]
    if index >= 0:
        return dataclasses.replace(problem, index=index)
    t = items[problem.index][1].t
    return Problem(
        None,
        "measurements",
        (
            f"a measurement at t={t!r} that an earlier batch applied is refused when late data makes the lag "
            f"window filter it again: {problem.field}: {problem.reason}"
        ),
    )


def _extend(window: _Window, observations: Sequence[Observation]) -> None:
    """Append observations (in time order, all newer than the window's epochs) as epochs."""
    epoch: list[Observation] = []
    for observation in observations:
        if not _finite(observation.t):
            continue
        if epoch and observation.t != epoch[0].t:
            _append_epoch(window, epoch)
            epoch = []
        epoch.append(observation)
    if epoch:
        _append_epoch(window, epoch)


def _append_epoch(window: _Window, epoch: list[Observation]) -> None:
    t = epoch[0].t
    window.times.append(t)
    window.records.append(encode_epoch(epoch))
    if window.newest is None or t > window.newest:
        window.newest = t


def _maybe_checkpoint(window: _Window, t: float | None, state: bytes) -> None:
    """Keep ``state`` (filtered up to ``t``) as a checkpoint if it is far enough after the last one."""
    if t is None:
        return
    last = window.checkpoints[-1].t
    spacing = window.options["max_delay_s"] / CHECKPOINTS_PER_WINDOW
    if last is None or t - last >= spacing:
        window.checkpoints.append(_Checkpoint(t, state))


def _prune(window: _Window) -> None:
    """Drop what no accepted late measurement can need (see ``_pruning``)."""
    if window.newest is None:
        return
    keep, start = _pruning(
        window.newest,
        window.options["max_delay_s"],
        window.options["max_window_epochs"],
        [c.t for c in window.checkpoints],
        window.times,
    )
    if keep is None:
        window.checkpoints = [_Checkpoint(window.newest, window.current)]
        window.times, window.records = [], []
    elif keep or start:
        window.checkpoints = window.checkpoints[keep:]
        window.times, window.records = window.times[start:], window.records[start:]


def _pruning(
    newest: float, delay: float, limit: int, checkpoint_times: Sequence[float | None], times: Sequence[float]
) -> tuple[int | None, int]:
    """What stays of a window: the base becomes the latest checkpoint from before ``newest - max_delay_s``,
    and while the window holds more than ``max_window_epochs`` epochs the base moves on. Returns the
    index of the new base and of its first epoch after it; (None, 0) when no checkpoint is left (the
    current state becomes the base, with no epochs)."""
    floor = newest - delay
    keep = 0
    for i, t in enumerate(checkpoint_times):
        if t is None or t < floor:
            keep = i
    while True:
        t = checkpoint_times[keep]
        start = 0 if t is None else bisect.bisect_right(times, t)
        if len(times) - start <= limit:
            return keep, start
        if keep + 1 < len(checkpoint_times):
            keep += 1
            continue
        return None, 0
