"""Session operations behind the routes: create, describe, delete, and apply a batch.

The batch path is all or nothing. The whole body is validated (pydantic, then the pipeline), the
filter runs in a worker thread on a copy of the state, and the new state, counters and response
are written in one compare-and-set on the record's version. A failed batch writes nothing. Within
a process a per-session lock keeps two requests for one session from interleaving; across worker
processes a lost compare-and-set reloads the session and starts over.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import time
from typing import Any

import pydantic_core

from edgepos.api.admission import admit_batch, too_heavy_options
from edgepos.api.auth import INVALID_CREDENTIAL, hash_token, new_session_token, superseded_error
from edgepos.api.base_stations import batch_corrections, check_base_station
from edgepos.api.context import AppContext
from edgepos.api.convert import fix_to_json, fixes_bytes, joined_batch_body
from edgepos.api.ephemerides import LoadedEphemerides, satellite_problems
from edgepos.api.errors import ApiError, pipeline_problems
from edgepos.api.measurement_schemas import BatchIn
from edgepos.api.schemas import (
    FixOut,
    ProblemModel,
    SessionCreate,
    SessionCreated,
    SessionList,
    SessionListItem,
    SessionOut,
    TrackOut,
)
from edgepos.api.streams import fix_event_data, fix_event_prefix
from edgepos.core.errors import EstimationError
from edgepos.core.observations import (
    PseudorangeObservation,
    RsuObservation,
    RsuRangeObservation,
    V2vRangeObservation,
)
from edgepos.core.state import StateFormatError
from edgepos.pipelines import cost, tracks
from edgepos.pipelines.base import (
    Fix,
    InitialState,
    NeighbourTrack,
    Pipeline,
    PipelineInputError,
    Problem,
    StaticEnvironment,
    ensure_finite_fixes,
)
from edgepos.store.base import (
    SessionRecord,
    SessionSummary,
    StoreUnavailable,
    TooManySessions,
    VehicleNotRegistered,
)
from edgepos.store.fixlog import NewFix

logger = logging.getLogger("edgepos.api")

TOO_MANY_SESSIONS_RETRY_S = 30
"""Retry-After (s) sent with 429 too_many_sessions: idle sessions expire and free their slots over time."""

MAX_ATTEMPTS = 8
"""Compare-and-set attempts per batch before answering 503 (only other workers can cause a retry)."""


def _pipeline(context: AppContext, name: str) -> Pipeline:
    pipeline = context.pipelines.get(name)
    if pipeline is None:
        raise ApiError("unavailable", f"this server no longer offers the session's pipeline {name!r}")
    return pipeline


def _resolve_and_create(
    pipeline: Pipeline, body: SessionCreate, budget_s: float
) -> tuple[dict[str, Any], bytes]:
    """Effective options and the initial state (runs in the scheduler's lane: it may build filters).
    Options under which one epoch of the most measurements a batch may carry per epoch would cost
    more CPU than ``budget_s`` are refused before anything is built."""
    try:
        options = pipeline.resolve_options(body.options)
    except EstimationError as error:  # a parameter the estimation core refuses
        raise PipelineInputError([_problem("options", str(error))]) from None
    epoch_s = cost.epoch_cost_s(pipeline.name, options)
    if epoch_s > budget_s:
        raise PipelineInputError(
            [_problem("options", too_heavy_options(pipeline.name, options, epoch_s, budget_s))]
        )
    initial = None
    if body.initial_state is not None:
        initial = InitialState(**body.initial_state.model_dump())
    try:
        state = pipeline.create(options, initial)
    except EstimationError as error:
        raise PipelineInputError([_problem("initial_state", str(error))]) from None
    return options, state


def _unreadable_state(session_id: str, error: StateFormatError) -> ApiError:
    """A stored state this server cannot read (written by an incompatible version, or damaged): the
    vehicle is told to start over instead of getting a 500 on every call."""
    logger.warning(
        "unreadable session state",
        extra={"event": "state_unreadable", "session_id": session_id, "error": str(error)},
    )
    return ApiError(
        "conflict",
        f"this server cannot read the session's stored filter state ({error}); it was probably written by an "
        "incompatible edgepos version: delete the session and open a new one",
    )


def _problem(field: str, reason: str) -> Problem:
    return Problem(None, field, reason)


async def create_session(
    context: AppContext, body: SessionCreate, vehicle_key_hash: str | None = None
) -> SessionCreated:
    """Open the vehicle's one live session, superseding any older one. With ``vehicle_key_hash`` (a
    registry key opened it) the store re-checks that the key is still the vehicle's in the same atomic
    step, so a key revoked or rotated meanwhile opens nothing."""
    pipeline = context.pipelines.get(body.pipeline)
    if pipeline is None:
        known = ", ".join(sorted(context.pipelines))
        raise ApiError(
            "invalid_request",
            f"unknown pipeline {body.pipeline!r}",
            [ProblemModel(index=None, field="pipeline", reason=f"unknown pipeline; available: {known}")],
        )
    budget_s = context.settings.batch_cpu_budget_s
    try:
        async with context.scheduler.hold(f"vehicle:{body.vehicle_id}"):
            options, state = await context.scheduler.run(
                body.vehicle_id, 0.0, pipeline.name, _resolve_and_create, pipeline, body, budget_s
            )
    except PipelineInputError as error:
        raise ApiError(
            "invalid_request", "the session options are invalid", pipeline_problems(error.problems)
        ) from None
    await check_base_station(context.store, options)
    session_id = context.store.new_session_id(body.vehicle_id)
    token = new_session_token(session_id)
    now = context.store.clock()
    record = SessionRecord(
        session_id=session_id,
        vehicle_id=body.vehicle_id,
        pipeline=pipeline.name,
        options=options,
        token_hash=hash_token(token),
        state=state,
        created_at=now,
        updated_at=now,
    )
    try:
        superseded = await context.store.create(
            record, context.settings.max_sessions, vehicle_key_hash=vehicle_key_hash
        )
    except VehicleNotRegistered:
        raise ApiError(
            "unauthorized", "the bearer credential is not valid (unknown, revoked or expired key or token)"
        ) from None
    except TooManySessions as error:
        raise ApiError(
            "too_many_sessions",
            f"the server holds its maximum of {error.limit} sessions (EDGEPOS_MAX_SESSIONS); "
            "delete idle sessions or retry later",
            headers={"Retry-After": str(TOO_MANY_SESSIONS_RETRY_S)},
        ) from None
    if superseded is not None:
        context.metrics.sessions_superseded.inc()
        logger.info(
            "session superseded",
            extra={"event": "session_superseded", "session_id": superseded, "superseded_by": session_id},
        )
    logger.info("session created", extra={"event": "session_created", "session_id": session_id})
    return SessionCreated(
        superseded=superseded,
        session_id=session_id,
        token=token,
        vehicle_id=body.vehicle_id,
        pipeline=pipeline.name,
        options=options,
        created_at=now,
    )


async def _session_gone(context: AppContext, session_id: str, token_checked: bool = False) -> ApiError:
    """409 superseded when a newer session of the vehicle replaced this one, else 404; or, for a batch
    whose session token was checked against a record of a session gone since (deleted, revoked, expired;
    the record may be the one this worker cached), 401 as the token check now answers."""
    superseded = await context.store.supersession(session_id)
    if superseded is not None:
        return superseded_error(session_id, superseded.superseded_by)
    if token_checked:
        return ApiError("unauthorized", INVALID_CREDENTIAL)
    return ApiError("not_found", f"no session {session_id!r} (it may have expired or been deleted)")


def _list_item(summary: SessionSummary) -> SessionListItem:
    last_fix_t, status = None, "new"
    if summary.last_fix is not None:
        fix = json.loads(summary.last_fix)
        last_fix_t, status = fix.get("t"), fix.get("status", "new")
    return SessionListItem(
        session_id=summary.session_id,
        vehicle_id=summary.vehicle_id,
        pipeline=summary.pipeline,
        created_at=summary.created_at,
        updated_at=summary.updated_at,
        last_seq=summary.last_seq,
        batches=summary.batches,
        epochs=summary.epochs,
        last_fix_t=last_fix_t,
        status=status,
    )


async def list_sessions(
    context: AppContext, after: str | None, limit: int, pipeline: str | None, vehicle_id: str | None
) -> SessionList:
    page = await context.store.list_sessions(
        after=after, limit=limit + 1, pipeline=pipeline, vehicle_id=vehicle_id
    )
    more = len(page) > limit
    page = page[:limit]
    return SessionList(
        sessions=[_list_item(summary) for summary in page],
        next_after=page[-1].session_id if more else None,
    )


async def describe_session(context: AppContext, session_id: str) -> SessionOut:
    record = await context.store.get(session_id)
    if record is None:
        raise await _session_gone(context, session_id)
    try:
        summary = _pipeline(context, record.pipeline).summarise(record.state)
    except StateFormatError as error:
        raise _unreadable_state(session_id, error) from None
    return SessionOut(
        session_id=record.session_id,
        vehicle_id=record.vehicle_id,
        pipeline=record.pipeline,
        options=record.options,
        last_seq=record.last_seq,
        batches=record.batches,
        epochs=record.epochs,
        initialised=summary.initialised,
        t=summary.t,
        model_probabilities=summary.model_probabilities,
        last_fix=None if record.last_fix is None else FixOut.model_validate_json(record.last_fix),
        created_at=record.created_at,
        updated_at=record.updated_at,
    )


async def delete_session(context: AppContext, session_id: str) -> None:
    # The store withdraws the vehicle's published track with it: neighbours stop ranging against it.
    if not await context.store.delete(session_id):
        raise await _session_gone(context, session_id)
    logger.info("session deleted", extra={"event": "session_deleted", "session_id": session_id})


def batch_hash(batch: BatchIn) -> str:
    """Digest of the batch's content (not its bytes): a retry with other whitespace still matches.

    The content is the model's JSON, ``batch.model_dump_json()``'s very bytes (a test holds them to it, so
    stored digests keep matching across versions), written from the models' field dicts: the batch and
    measurement models have no serialisers, aliases or computed fields, and their ``__dict__`` holds their
    fields in declaration order, so pydantic-core writes the same JSON from the plain values, in about
    three quarters of the time the models' serialiser takes."""
    content = {**batch.__dict__, "measurements": [measurement.__dict__ for measurement in batch.measurements]}
    return hashlib.sha256(pydantic_core.to_json(content)).hexdigest()


def _replay_or_refuse(record: SessionRecord, batch: BatchIn, digest: str) -> bytes | None:
    """The stored response for a retried last batch; None for the next seq; 409 otherwise."""
    expected = record.last_seq + 1
    if batch.seq == expected:
        return None
    if batch.seq == record.last_seq:
        same = record.last_request_hash is not None and hmac.compare_digest(record.last_request_hash, digest)
        if same and record.last_response is not None:
            return record.last_response
        reason = f"seq {batch.seq} was already applied with a different body; the next seq is {expected}"
    elif batch.seq < record.last_seq:
        last = record.last_seq
        reason = f"seq {batch.seq} is older than the last applied seq {last}; the next seq is {expected}"
    else:
        reason = f"seq {batch.seq} skips ahead; the next seq is {expected}"
    raise ApiError("conflict", reason, [ProblemModel(index=None, field="seq", reason=reason)])


def _check_types(pipeline: Pipeline, batch: BatchIn, kinds: set[str]) -> None:
    """422 naming each measurement of a type the pipeline does not use (``kinds``: the types the batch has)."""
    if kinds.issubset(pipeline.measurement_kinds):
        return
    problems = [
        ProblemModel(
            index=index,
            field=f"measurements[{index}].type",
            reason=f"the {pipeline.name} pipeline does not use {measurement.type!r} measurements",
        )
        for index, measurement in enumerate(batch.measurements)
        if measurement.type not in pipeline.measurement_kinds
    ]
    if problems:
        raise ApiError("invalid_request", "the batch has measurements this session cannot use", problems)


async def apply_batch(
    context: AppContext, session_id: str, batch: BatchIn, prefetched: SessionRecord | None = None
) -> bytes:
    """Apply ``batch`` exactly once and return the response body (JSON bytes).

    ``prefetched`` is the record the token check just read (one store read per batch instead of two):
    it is trusted only to apply the next seq, which the compare-and-set then confirms is still current;
    a replay or a refusal is decided on a fresh read."""
    limit = context.settings.max_batch_measurements
    if len(batch.measurements) > limit:
        count = len(batch.measurements)
        reason = f"at most {limit} measurements per batch (EDGEPOS_MAX_BATCH_MEASUREMENTS), got {count}"
        problem = ProblemModel(index=None, field="measurements", reason=reason)
        raise ApiError("invalid_request", "the batch is too large", [problem])
    digest = batch_hash(batch)
    observations = [measurement.to_observation() for measurement in batch.measurements]
    # The kinds present first (one pass): most batches carry two or three, and the passes below are skipped
    # for the kinds they do not carry.
    kinds = {o.kind for o in observations}
    rsu_ids = _rsu_ids(observations) if not kinds.isdisjoint(_RSU_KINDS) else set()
    peer_ids = _peer_ids(observations) if V2vRangeObservation.kind in kinds else set()
    has_pseudoranges = PseudorangeObservation.kind in kinds
    # One place in the vehicle's line for the whole request: a vehicle that sends batches in parallel
    # gets 429 instead of holding the worker's admission slots while it waits for its own session.
    async with context.scheduler.hold(f"session:{session_id}"):
        return await _apply_in_turn(
            context,
            session_id,
            batch,
            digest,
            observations,
            kinds,
            rsu_ids,
            peer_ids,
            has_pseudoranges,
            prefetched,
        )


async def _apply_in_turn(
    context: AppContext,
    session_id: str,
    batch: BatchIn,
    digest: str,
    observations: list[Any],
    kinds: set[str],
    rsu_ids: set[str],
    peer_ids: set[str],
    has_pseudoranges: bool,
    prefetched: SessionRecord | None = None,
) -> bytes:
    metrics = context.metrics
    checked = prefetched is not None  # the token was checked against a record (perhaps a cached one)
    if context.store.locks.busy(session_id):
        prefetched = None  # another request of this session goes first: what the token check read is old
    for _attempt in range(MAX_ATTEMPTS):
        async with context.store.session_lock(session_id):
            record, prefetched = prefetched, None
            if (
                record is None or batch.seq != record.last_seq + 1
            ):  # only the next seq goes on a prefetched read
                record = await context.store.get(session_id)
            if record is None:
                raise await _session_gone(context, session_id, checked)
            try:
                replay = _replay_or_refuse(record, batch, digest)
            except ApiError:
                metrics.batches.labels("conflict").inc()
                raise
            if replay is not None:
                await context.store.make_durable(
                    session_id
                )  # the first attempt may have stored it without replicas
                metrics.batches.labels("replayed").inc()
                return replay
            pipeline = _pipeline(context, record.pipeline)
            _check_types(pipeline, batch, kinds)
            try:
                # Late measurements make the lag window filter some stored ones again: their RSUs and
                # neighbours are looked up too, and their cost counts against the budget.
                replayed = pipeline.replayed_observations(record.state, observations)
            except StateFormatError as error:
                raise _unreadable_state(session_id, error) from None
            cost_s = admit_batch(
                context.settings.batch_cpu_budget_s, pipeline.name, record.options, observations, replayed
            )
            if replayed:
                rsu_ids = rsu_ids | _rsu_ids(replayed)
                peer_ids = peer_ids | _peer_ids(replayed)
            # One read for the peers' tracks and, if this session publishes, its own (extended
            # after the batch); nothing at all for a batch of a non-cooperative session.
            wanted = peer_ids | ({record.vehicle_id} if pipeline.publishes_track else set())
            published = dict(await context.store.get_tracks(wanted)) if wanted else {}
            peers = {vehicle: published[vehicle] for vehicle in peer_ids if vehicle in published}
            rsus = dict(await context.store.get_rsus(rsu_ids)) if rsu_ids else {}
            # The site's ephemerides only for batches with pseudoranges: one digest read, parsed once
            # per worker and file.
            loaded: LoadedEphemerides | None = None
            if has_pseudoranges:
                loaded = await context.ephemerides.current(context.store, context.run_filter)
                _check_satellites(observations, loaded, record.options.get("systems"))
            # The reference station's corrections when the session asked for them: one store read of the
            # epochs this batch can use (two for base_station "nearest": the stations, then the window).
            differential = None
            if has_pseudoranges and record.options.get("base_station") is not None:
                differential = await batch_corrections(
                    context.store,
                    context.base_epochs,
                    record.options,
                    observations,
                    None if loaded is None else loaded.ephemerides,
                    record.last_fix,
                    _origin(context),
                )
            environment = StaticEnvironment(
                rsus,
                peers,
                record.vehicle_id,
                navigation=None if loaded is None else loaded.ephemerides,
                origin=_origin(context),
                differential=differential,
            )
            started = time.perf_counter()
            try:
                fixes, state = await context.scheduler.run(
                    record.vehicle_id,
                    cost_s,
                    pipeline.name,
                    pipeline.process,
                    record.state,
                    observations,
                    environment,
                )
            except PipelineInputError as error:
                metrics.batches.labels("rejected").inc()
                count = len(error.problems)
                raise ApiError(
                    "invalid_request",
                    f"the batch was refused ({count} problem{'s' if count != 1 else ''}); "
                    "the session is unchanged",
                    pipeline_problems(error.problems, "measurements", _wire_field_namer(batch)),
                ) from None
            except StateFormatError as error:
                metrics.batches.labels("failed").inc()
                raise _unreadable_state(session_id, error) from None
            except EstimationError as error:
                metrics.batches.labels("failed").inc()
                logger.warning(
                    "estimation failed",
                    extra={"event": "estimation_failed", "session_id": session_id, "error": str(error)},
                )
                raise ApiError(
                    "estimation_failed",
                    f"the filter could not process this batch: {error}; the session is unchanged",
                ) from None
            elapsed = time.perf_counter() - started
            # each fix written once: the answer, the fix events and the last fix are joined from these
            fix_json = fixes_bytes(fixes, batch.include_state, context.origin)
            stateless = fixes_bytes(fixes, False, context.origin) if batch.include_state else fix_json
            body = joined_batch_body(batch.seq, fix_json)
            last_fix = stateless[-1].decode() if stateless else record.last_fix
            updated = _applied(
                record,
                state=state,
                seq=batch.seq,
                digest=digest,
                body=body,
                epochs=sum(not fix.revised for fix in fixes),
                last_fix=last_fix,
                now=context.store.clock(),
            )
            # the fix events go with the write where the store can take them (one round trip), else after it
            events = _fix_events(record, batch.seq, fixes, stateless)
            store, in_write = context.store, context.store.fixes_in_write
            if in_write:
                applied = await store.compare_and_set(updated, record.version, events)
            else:
                applied = await store.compare_and_set(updated, record.version)
            if applied:
                metrics.observe_batch(len(fixes), elapsed)
                if not in_write:
                    context.streams.publish(events)
                if pipeline.publishes_track:
                    await _publish_track(context, record, published.get(record.vehicle_id), fixes)
                return body
            metrics.store_conflicts.inc()
    raise ApiError("unavailable", "the session kept changing under this request; retry the same batch")


def _applied(
    record: SessionRecord,
    *,
    state: bytes,
    seq: int,
    digest: str,
    body: bytes,
    epochs: int,
    last_fix: str | None,
    now: float,
) -> SessionRecord:
    """The record with the batch ``seq`` applied: ``dataclasses.replace(record, ...)`` with the new state,
    seq, request digest, stored answer, counters (``epochs`` new ones), last fix and time. Built from a copy
    of the frozen record's ``__dict__``, which is what ``replace`` gives a dataclass without
    ``__post_init__`` or init-less fields (as ``store.memory`` copies records; a test holds SessionRecord to
    that), at a fraction of its cost: its ``__init__`` sets the fifteen fields one ``object.__setattr__``
    at a time."""
    updated = object.__new__(SessionRecord)
    fields = updated.__dict__
    fields.update(record.__dict__)
    fields.update(
        state=state,
        last_seq=seq,
        last_request_hash=digest,
        last_response=body,
        batches=record.batches + 1,
        epochs=record.epochs + epochs,
        last_fix=last_fix,
        updated_at=now,
    )
    return updated


def _fix_events(
    record: SessionRecord, seq: int, fixes: list[Fix], stateless_json: list[bytes]
) -> list[NewFix]:
    """The batch's fixes (and their JSON with a null state) as events of the fix stream: appended with the
    batch's write by a store that can (``SessionStore.fixes_in_write``), else queued for this worker's
    publisher once the write applied, so the answer never waits for the stream (see api.streams)."""
    session_id, vehicle_id, pipeline = record.session_id, record.vehicle_id, record.pipeline
    prefix = fix_event_prefix(session_id, vehicle_id, pipeline, seq)
    return [
        NewFix(session_id, vehicle_id, pipeline, float(fix.t), fix_event_data(prefix, written))
        for fix, written in zip(fixes, stateless_json, strict=True)
    ]


_RSU_KINDS = frozenset({RsuObservation.kind, RsuRangeObservation.kind})


def _rsu_ids(observations: list[Any]) -> set[str]:
    return {o.rsu_id for o in observations if isinstance(o, (RsuObservation, RsuRangeObservation))}


def _peer_ids(observations: list[Any]) -> set[str]:
    return {o.peer_vehicle_id for o in observations if isinstance(o, V2vRangeObservation)}


def _check_satellites(observations: list[Any], loaded: LoadedEphemerides | None, systems_used: Any) -> None:
    """422 naming each pseudorange whose satellite state is unknown (no ephemeris, none sent)."""
    systems = [str(s) for s in systems_used] if isinstance(systems_used, list) else None
    problems = satellite_problems(observations, loaded, systems)
    if problems:
        count = len(problems)
        them = "it" if count == 1 else "them"
        what = "no ephemerides are loaded"
        if loaded is not None:
            what = f"the loaded ephemerides do not cover {them}"
        raise ApiError(
            "invalid_request",
            f"{count} pseudorange{'s have' if count != 1 else ' has'} no satellite position: {what}; "
            "the session is unchanged",
            problems,
        )


def _origin(context: AppContext) -> tuple[float, float, float] | None:
    origin = context.origin
    return None if origin is None else (origin.lat, origin.lon, origin.height)


def _wire_field_namer(batch: BatchIn) -> Any:
    """Renames a pipeline's observation field to the wire field of that measurement's type."""

    def rename(index: int, field: str) -> str:
        if 0 <= index < len(batch.measurements):
            names = getattr(batch.measurements[index], "WIRE_FIELDS", {})
            return str(names.get(field, field))
        return field

    return rename


async def _publish_track(
    context: AppContext, record: SessionRecord, previous: NeighbourTrack | None, fixes: list[Fix]
) -> None:
    """Make the vehicle's latest estimates readable by its neighbours' sessions (one atomic value).

    Runs right after the session's own write, under its lock. The batch is already applied, so a
    store that fails here is logged, not answered with an error: neighbours then see the previous
    track, which ages out by their max_neighbour_age, and the next batch publishes again."""
    track = tracks.publish(record.vehicle_id, previous, fixes)
    if track is None:
        return
    try:
        # Written only while this session is still the vehicle's live one: a superseded session's
        # late batch never mixes into its successor's track.
        await context.store.put_track(track, record.session_id)
    except StoreUnavailable as error:
        logger.warning(
            "track not published",
            extra={"event": "track_not_published", "session_id": record.session_id, "error": str(error)},
        )


async def session_track(context: AppContext, session_id: str, smoothed: bool) -> TrackOut:
    """The estimates of the session's lag window, filtered again from the window's start, or smoothed."""
    record = await context.store.get(session_id)
    if record is None:
        raise await _session_gone(context, session_id)
    pipeline = _pipeline(context, record.pipeline)
    if smoothed and not pipeline.smoother:
        smoothing = sorted(name for name, p in context.pipelines.items() if p.smoother)
        reason = f"the {pipeline.name} pipeline has no smoother (pipelines with one: {', '.join(smoothing)})"
        raise ApiError("invalid_request", reason, [ProblemModel(index=None, field="smoothed", reason=reason)])
    try:
        observations = pipeline.replayed_observations(record.state, None)
        start_t, end_t, window = pipeline.window_bounds(record.state)
    except StateFormatError as error:
        raise _unreadable_state(session_id, error) from None
    rsus = dict(await context.store.get_rsus(_rsu_ids(observations))) if observations else {}
    peer_ids = _peer_ids(observations)
    peers = dict(await context.store.get_tracks(peer_ids)) if peer_ids else {}
    loaded = None
    if any(isinstance(o, PseudorangeObservation) for o in observations):
        loaded = await context.ephemerides.current(context.store, context.run_filter)
    environment = StaticEnvironment(
        rsus,
        peers,
        record.vehicle_id,
        navigation=None if loaded is None else loaded.ephemerides,
        origin=_origin(context),
    )
    # A smoother filters forwards and then runs backwards: about twice a replay of the window.
    cost_s = (2.0 if smoothed else 1.0) * cost.batch_cost_s(pipeline.name, record.options, observations)
    try:
        fixes = await context.scheduler.run(
            record.vehicle_id,
            cost_s,
            pipeline.name,
            _track_fixes,
            pipeline,
            record.state,
            environment,
            smoothed,
        )
    except StateFormatError as error:
        raise _unreadable_state(session_id, error) from None
    except (PipelineInputError, EstimationError) as error:
        raise ApiError(
            "estimation_failed", f"the window's track could not be computed now: {error}"
        ) from None
    origin = context.origin
    return TrackOut.model_validate(
        {
            "session_id": session_id,
            "pipeline": pipeline.name,
            "smoothed": smoothed,
            "max_delay_s": window.get("max_delay_s", 0.0),
            "start_t": start_t,
            "end_t": end_t,
            "fixes": [fix_to_json(fix, True, origin) for fix in fixes],
        }
    )


def _track_fixes(
    pipeline: Pipeline, state: bytes, environment: StaticEnvironment, smoothed: bool
) -> list[Fix]:
    """Runs in the scheduler's lane: the window's fixes, each checked finite."""
    return ensure_finite_fixes(pipeline.track(state, environment, smoothed))
