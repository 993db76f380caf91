"""Physical plausibility of every pipeline's fixes: one wrapper the registry puts around each pipeline.

A filter can report finite but absurd estimates: started far from its measurements it runs off at
3e7 m/s, predicted across a day-long gap it lands 1e10 m away, and still says ``tracking``. A vehicle
on a road cannot do that, so :class:`Plausible` checks each fix the inner pipeline produces against
bounds that no road vehicle exceeds, whatever the filter:

* ``max_speed_mps``: the fix's speed;
* ``max_acceleration_mps2``: the velocity change from the previous fix over the time between them;
* a position jump: the displacement from the previous fix against the one the two velocities imply
  (trapezoid rule), beyond ``max_speed_mps`` times the interval (plus half the acceleration bound
  times its square): the estimate moved where no vehicle could have gone;
* ``site_radius_m``: the position's distance from the site origin (0, 0).

Speed, acceleration and jump are judged beyond the filter's own uncertainty: ``SIGMA_ALLOWANCE``
standard deviations of the fix's (and the previous fix's) velocity and position covariance are added
to the bound, the two fixes taken as independent (lenient on purpose). A filter that is converging
after initialisation, or whose velocity is a noisy difference of positions (v2v_coop's ``gps``
method), says how uncertain it is and is not flagged; the runaway estimates this is for (3e7 m/s with
a velocity sigma of 400 m/s) are far beyond any allowance. The site radius is a hard bound.

The previous fix is the session's latest judged fix with finite kinematics, kept across batches in
the state. A fix with status ``initialised`` starts a new track (the pipeline restarted on purpose,
e.g. after ``max_gap``): only speed and site radius apply to it. The first implausible fix gets the
status ``diverged`` and a ``divergence`` text saying what was exceeded and what was done:

* ``on_divergence="reset"`` (default): the inner state is created anew (no initial state), so the
  pipeline initialises itself again from its next measurements, and the rest of the batch (epochs
  after the diverged one) is processed again from that fresh state. One more ``inner.process`` call
  when it happens; should the re-processed part diverge again, later re-processing goes in chunks of
  1, 2, 4, ... epochs, so that a batch that diverges at every epoch costs a bounded multiple of a plain
  run, never the square of its length.
* ``on_divergence="report"``: the fix is marked and filtering continues from the inner state as it is;
  the next fix is compared with the reported one (so a single jump is reported once, a runaway
  estimate at every fix).

A ``diverged`` fix is never published as the vehicle's track (``tracks.track_points`` skips it).

Before filtering, times: a batch any of whose epochs is more than ``max_time_jump_s`` after the
previous one (the session's last epoch, or the batch's previous epoch) is refused, naming the
observations. Refused, not started anew as ``max_gap`` does: a session cannot go back in time, so
accepting a jump to a bogus far-future t (a clock in milliseconds, garbage, t = 1e10, the largest the
API takes) would leave the session refusing every later, correct measurement as "older than its last
epoch" for good; refusing leaves it where it was, able to take the next correct batch, and the 422
says what to do if the vehicle's clock really moved on (open a new session). The default bound, one
hour, is the default session TTL: a session idle longer than that has expired anyway. (These time
problems are found before the inner pipeline validates the batch, so such a 422 lists only them.)

At creation an initial state farther than ``site_radius_m`` from the site origin, or faster than
``max_speed_mps``, is refused (422 naming ``initial_state.x``/``.y`` or ``.vx``/``.vy``).

State: the inner pipeline's bytes behind a small fixed-size envelope, ``b"EPPL" | version byte |
these options, the session's last epoch time and the last judged fix as float64 | inner state`` (see
``_ENVELOPE``). A state without the envelope (written before this wrapper existed) is read as the
inner pipeline's, with the default options; it gets the envelope when the next batch is applied.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import struct
import typing
from collections.abc import Mapping, Sequence
from typing import Any, cast

import numpy as np

from edgepos.core.errors import EstimationError
from edgepos.core.observations import Observation
from edgepos.core.state import StateFormatError
from edgepos.pipelines.base import (
    Environment,
    Fix,
    InitialState,
    OptionSpec,
    Pipeline,
    PipelineInputError,
    Problem,
    StateSummary,
    is_finite_number,
)
from edgepos.pipelines.wrapping import WrappingPipeline

MAGIC = b"EPPL"
VERSION = 1

SIGMA_ALLOWANCE = 4.0
"""How many standard deviations of the filter's own uncertainty a velocity change or position jump may
exceed the physical bound by before it counts as implausible (4: a chi-square 2-dof tail of 3e-4)."""

DIVERGED = "diverged"

OPTION_SPECS: tuple[OptionSpec, ...] = (
    OptionSpec(
        "max_speed_mps",
        "number",
        150.0,
        "Plausibility: a fix faster than this (m/s) is reported 'diverged' (540 km/h: no road vehicle, "
        "with room for filter noise); an initial state faster than this is refused.",
        1.0,
        1000.0,
    ),
    OptionSpec(
        "max_acceleration_mps2",
        "number",
        100.0,
        "Plausibility: a velocity change between consecutive fixes faster than this (m/s^2), beyond "
        f"{SIGMA_ALLOWANCE:g} sigma of the filter's velocity uncertainty, is reported 'diverged'. Road vehicles "
        "brake at about 1 g (10 m/s^2), but a filter's velocity estimate also jumps with its measurement "
        "corrections: up to 60 m/s^2 at 20 Hz in the RSU paper's scenario with a mismatched motion model.",
        1.0,
        1000.0,
    ),
    OptionSpec(
        "site_radius_m",
        "number",
        50_000.0,
        "Plausibility: a fix farther than this (m) from the site origin (0, 0) is reported 'diverged'; an "
        "initial state farther than this is refused. 2e6 covers every coordinate the API accepts.",
        10.0,
        2.0e6,
    ),
    OptionSpec(
        "max_time_jump_s",
        "number",
        3600.0,
        "A batch with an epoch more than this (s) after the session's last epoch, or after the batch's "
        "previous epoch, is refused (422): a clock error must not move the session's clock past all "
        "later measurements. Open a new session when the clock really jumped.",
        1.0,
        604800.0,
    ),
    OptionSpec(
        "on_divergence",
        "string",
        "reset",
        "What a 'diverged' fix does: reset (the pipeline starts again from its next measurements; the "
        "rest of the batch is filtered from there) or report (the fix is marked, filtering continues).",
        choices=("reset", "report"),
    ),
)
DEFAULTS: dict[str, Any] = {spec.name: spec.default for spec in OPTION_SPECS}


class _Point(typing.NamedTuple):
    """What is kept of the last judged fix: time, position, velocity and their variances (traces). A
    named tuple: one is made per judged fix, and a frozen dataclass takes several times as long."""

    t: float
    x: float
    y: float
    vx: float | None
    vy: float | None
    position_var: float
    velocity_var: float


_new_point = tuple.__new__
"""``_new_point(_Point, values)``: a ``_Point`` without the Python frame of its generated ``__new__``."""


@dataclasses.dataclass
class _Envelope:
    options: dict[str, Any]
    t: float | None  # the session's last epoch (None before any, or unknown for a state without envelope)
    last: _Point | None  # the last judged fix with finite kinematics
    clock_reset: bool  # a reset left the inner state without a clock: the wrapper keeps times monotone
    known: bool = True  # False for a state written before this wrapper: t must come from the inner state


# The envelope, little-endian: magic, version; the options max_speed_mps, max_acceleration_mps2,
# site_radius_m, max_time_jump_s (float64) and on_divergence (byte: index in _POLICIES); the session's
# last epoch t (NaN: none); flags (byte: _CLOCK_RESET, _HAS_LAST); the last judged fix t, x, y, vx, vy
# (NaN: none), position and velocity variance. Fixed size, packed and read in a microsecond (a JSON
# header cost 30 us a batch).
_ENVELOPE = struct.Struct("<4sB4dBdB7d")
_POLICIES = ("reset", "report")
_NUMBERS = ("max_speed_mps", "max_acceleration_mps2", "site_radius_m", "max_time_jump_s")
_CLOCK_RESET, _HAS_LAST = 1, 2
_NAN = math.nan


def wrap(envelope: _Envelope, inner_state: bytes) -> bytes:
    options, last = envelope.options, envelope.last
    flags = (_CLOCK_RESET if envelope.clock_reset else 0) | (_HAS_LAST if last is not None else 0)
    point = (
        (0.0,) * 7
        if last is None
        else (
            last.t,
            last.x,
            last.y,
            _NAN if last.vx is None else last.vx,
            _NAN if last.vy is None else last.vy,
            last.position_var,
            last.velocity_var,
        )
    )
    header = _ENVELOPE.pack(
        MAGIC,
        VERSION,
        *(float(options[name]) for name in _NUMBERS),
        _POLICIES.index(options["on_divergence"]),
        _NAN if envelope.t is None else envelope.t,
        flags,
        *point,
    )
    return header + inner_state


def unwrap(state: bytes) -> tuple[_Envelope, bytes]:
    """The envelope and the inner state; a state without envelope gets the default options."""
    if state[: len(MAGIC)] != MAGIC:
        return _Envelope(dict(DEFAULTS), None, None, False, known=False), state
    if len(state) < _ENVELOPE.size:
        raise StateFormatError("plausibility envelope is truncated")
    _, version, speed, accel, radius, jump, policy, t, flags, *point = _ENVELOPE.unpack_from(state)
    if version != VERSION:
        raise StateFormatError(f"plausibility envelope version {version} is not {VERSION}")
    if policy >= len(_POLICIES) or not all(map(math.isfinite, (speed, accel, radius, jump))) or flags > 3:
        raise StateFormatError("plausibility envelope is corrupt")
    options = {
        "max_speed_mps": speed,
        "max_acceleration_mps2": accel,
        "site_radius_m": radius,
        "max_time_jump_s": jump,
        "on_divergence": _POLICIES[policy],
    }
    last = None
    if flags & _HAS_LAST:
        pt, x, y, vx, vy, position_var, velocity_var = point
        last = _Point(
            pt,
            x,
            y,
            None if math.isnan(vx) else vx,
            None if math.isnan(vy) else vy,
            position_var,
            velocity_var,
        )
    envelope = _Envelope(options, None if math.isnan(t) else t, last, bool(flags & _CLOCK_RESET))
    return envelope, state[_ENVELOPE.size :]


def _own_options(options: Mapping[str, Any]) -> dict[str, Any]:
    """This wrapper's options out of a session's resolved options (defaults for missing ones)."""
    return {name: options.get(name, default) for name, default in DEFAULTS.items()}


class Plausible(WrappingPipeline):
    """``inner`` with physical plausibility checks of its fixes and times (see the module docstring)."""

    own_specs = OPTION_SPECS

    # -- sessions ----------------------------------------------------------------------------------
    def create(self, options: Mapping[str, Any], initial: InitialState | None) -> bytes:
        own = _own_options(options)
        problems = [] if initial is None else _initial_problems(initial, own)
        try:
            inner_state = self.inner.create(self.inner_options(options), initial)
        except PipelineInputError as error:
            raise PipelineInputError([*problems, *error.problems]) from None
        if problems:
            raise PipelineInputError(problems)
        return wrap(_Envelope(own, None, None, False), inner_state)

    def summarise(self, state: bytes) -> StateSummary:
        envelope, inner_state = unwrap(state)
        summary = self.inner.summarise(inner_state)
        return dataclasses.replace(
            summary,
            t=summary.t if summary.t is not None else envelope.t,
            options={**summary.options, **envelope.options},
        )

    def smooth(
        self,
        state: bytes,
        observations: Sequence[Observation],
        environment: Environment,
        lag_s: float | None = None,
    ) -> list[Fix]:
        """The inner pipeline's smoothed fixes (not judged: a smoother runs over fixes already judged)."""
        _, inner_state = unwrap(state)
        return self.inner.smooth(inner_state, observations, environment, lag_s)

    def written_records(self, observations: Sequence[Observation]) -> tuple[np.ndarray, list[int]] | None:
        """The inner pipeline's ``written_records`` of ``observations`` (None when it has none)."""
        writer = getattr(self.inner, "written_records", None)
        return None if writer is None else cast(tuple[np.ndarray, list[int]] | None, writer(observations))

    # -- batches -----------------------------------------------------------------------------------
    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        envelope, inner_state = unwrap(state)
        if not envelope.known:  # a state from before this wrapper: its clock is the inner pipeline's
            envelope.t = self.inner.summarise(inner_state).t
            envelope.known = True
        latest = _check_times(envelope, observations)
        judge = _Judge(self.inner, envelope, observations, environment)
        try:
            fixes, new_inner = self.inner.process(inner_state, observations, environment)
        except EstimationError:
            # Perhaps an earlier epoch had run off and the filter failed on a later one: filtered again
            # a few epochs at a time, the run-off fix is judged (and reset) before the failure; a
            # failure with nothing implausible before it is raised again.
            fixes, new_inner = judge.run(None, inner_state)
        else:
            if not fixes and new_inner == inner_state:
                return fixes, state  # nothing happened (an empty batch): the very same bytes
            fixes, new_inner = judge.run(fixes, new_inner)
        if latest is not None:
            envelope.t = latest if envelope.t is None else max(envelope.t, latest)
        return fixes, wrap(envelope, new_inner)


# -- checks before filtering ------------------------------------------------------------------------
def _initial_problems(initial: InitialState, options: Mapping[str, Any]) -> list[Problem]:
    problems = []
    radius = options["site_radius_m"]
    distance = math.hypot(initial.x, initial.y)
    if not distance <= radius:
        reason = (
            f"the initial position is {distance:.6g} m from the site origin, beyond site_radius_m {radius:g} m "
            "(give site-frame coordinates, or raise options.site_radius_m)"
        )
        problems += [Problem(None, "initial_state.x", reason), Problem(None, "initial_state.y", reason)]
    speed = math.hypot(initial.vx, initial.vy)
    if not speed <= options["max_speed_mps"]:
        reason = f"the initial speed {speed:.6g} m/s exceeds max_speed_mps {options['max_speed_mps']:g} m/s"
        problems += [Problem(None, "initial_state.vx", reason), Problem(None, "initial_state.vy", reason)]
    return problems


def _check_times(envelope: _Envelope, observations: Sequence[Observation]) -> float | None:
    """Refuse epochs more than max_time_jump_s after the previous one, and (after a reset left the
    inner pipeline without a clock) observations older than the session's last epoch. Returns the
    batch's latest (finite) time, None for an empty batch."""
    bound = envelope.options["max_time_jump_s"]
    last = envelope.t
    problems: list[Problem] = []
    if envelope.clock_reset and last is not None:
        for index, observation in enumerate(observations):
            if is_finite_number(observation.t) and observation.t < last:
                problems.append(
                    Problem(
                        index, "t", f"{observation.t!r} is older than the session's last epoch t={last!r}"
                    )
                )
    if not problems and observations and type(observations[0].t) is float:
        oldest = newest = observations[0].t
        for observation in observations:
            t = observation.t
            if type(t) is not float:  # ints and anything else: the general path below
                break
            if t < oldest:
                oldest = t
            elif t > newest:
                newest = t
        else:
            # NaN and infinities fail every comparison with the bound
            if newest - oldest <= bound and (last is None or newest - last <= bound):
                return newest  # the usual batch: no gap can be longer than the bound
    times = sorted({t for t in {o.t for o in observations} if is_finite_number(t)})
    latest = times[-1] if times else None
    if not problems and (
        not times or (times[-1] - times[0] <= bound and (last is None or times[-1] - last <= bound))
    ):
        return latest  # the usual batch: no gap can be longer than the bound
    jumps: dict[float, tuple[float, str]] = {}
    previous, where = last, "the session's last epoch"
    for t in times:
        if previous is not None and t - previous > bound:
            jumps[t] = (previous, where)
        if previous is None or t > previous:
            previous, where = t, "the batch's previous epoch"
    for index, observation in enumerate(observations):
        if observation.t in jumps:
            before, what = jumps[observation.t]
            problems.append(
                Problem(
                    index,
                    "t",
                    (
                        f"{observation.t!r} is {observation.t - before:.6g} s after {what} t={before!r}, more than "
                        f"max_time_jump_s {bound:g} s: a clock error? (if the vehicle's clock really moved on, open a "
                        "new session)"
                    ),
                )
            )
    if problems:
        raise PipelineInputError(sorted(problems, key=lambda p: p.index if p.index is not None else -1))
    return latest


# -- checks of the fixes ----------------------------------------------------------------------------
def _finite(*values: float | None) -> bool:
    for value in values:
        if value is not None and not math.isfinite(value):
            return False
    return True


def _velocity_variance(fix: Fix) -> float:
    """Trace of the fix's 2x2 velocity covariance (m^2/s^2), 0 when the fix does not give it."""
    if fix.kinematic_cov is not None:
        return float(fix.kinematic_cov[2][2] + fix.kinematic_cov[3][3])
    if fix.state_cov is not None:
        names = fix.state_components
        for east, north in (("xv", "yv"), ("v_east", "v_north")):
            if east in names and north in names:
                i, j = names.index(east), names.index(north)
                return float(fix.state_cov[i][i] + fix.state_cov[j][j])
    return 0.0


def _position_variance(fix: Fix) -> float:
    if fix.position_cov is None:
        return 0.0
    return float(fix.position_cov[0][0] + fix.position_cov[1][1])


def _point(fix: Fix) -> _Point | None:
    """What is kept of a fix for the next one's checks; None without finite kinematics."""
    if fix.x is None or fix.y is None:
        return None
    return _point_of(fix, fix.x, fix.y, _position_variance(fix), _velocity_variance(fix))


def _point_of(fix: Fix, x: float, y: float, position_var: float, velocity_var: float) -> _Point | None:
    """``_point`` of a fix with a position (``x``, ``y``: its own, passed known not None), its
    variances given."""
    # finite, all of them: a finite sum is (NaN and infinities carry through a sum), else one by one
    total = fix.t + x + y + position_var + velocity_var
    if fix.vx is not None:
        total += fix.vx
    if fix.vy is not None:
        total += fix.vy
    if not math.isfinite(total) and not _finite(fix.t, x, y, fix.vx, fix.vy, position_var, velocity_var):
        return None
    if position_var < 0.0 or velocity_var < 0.0:  # round-off below zero kept as 0 (two max() calls a fix)
        position_var, velocity_var = max(position_var, 0.0), max(velocity_var, 0.0)
    return _new_point(_Point, (fix.t, x, y, fix.vx, fix.vy, position_var, velocity_var))


def implausibility(fix: Fix, last: _Point | None, options: Mapping[str, Any]) -> str | None:
    """Why ``fix`` is physically implausible after ``last`` (the previous judged fix), or None."""
    if fix.x is None or fix.y is None:
        return None  # no estimate (uninitialised): nothing to judge
    return _implausibility(
        fix, fix.x, fix.y, last, _bounds(options), _position_variance(fix), _velocity_variance(fix)
    )


def _bounds(options: Mapping[str, Any]) -> tuple[float, float, float]:
    """The bounds a fix is judged against: max_speed_mps, max_acceleration_mps2 and site_radius_m (read
    from the options once per batch, not once per fix)."""
    return options["max_speed_mps"], options["max_acceleration_mps2"], options["site_radius_m"]


def _judged(
    fix: Fix, last: _Point | None, bounds: tuple[float, float, float]
) -> tuple[str | None, _Point | None]:
    """``implausibility`` and ``_point`` of ``fix`` together (what ``_Judge`` asks of every fix), the fix's
    variances read once; ``bounds`` from ``_bounds``."""
    x, y = fix.x, fix.y
    if x is None or y is None:
        return None, None
    # _position_variance and _velocity_variance, the usual fix's (both blocks given) read here
    position_cov, kinematic_cov = fix.position_cov, fix.kinematic_cov
    position_var = 0.0 if position_cov is None else float(position_cov[0][0] + position_cov[1][1])
    if kinematic_cov is None:
        velocity_var = _velocity_variance(fix)
    else:
        velocity_var = float(kinematic_cov[2][2] + kinematic_cov[3][3])
    point = _point_of(fix, x, y, position_var, velocity_var)
    if point is None:  # something is not finite: the check looks at each value
        return _implausibility(fix, x, y, last, bounds, position_var, velocity_var), None
    # a point is kept only when its position and velocity are finite, as the check's first test asks
    return _beyond_bounds(fix, x, y, last, bounds, position_var, velocity_var), point


def _implausibility(
    fix: Fix,
    x: float,
    y: float,
    last: _Point | None,
    bounds: tuple[float, float, float],
    position_var: float,
    velocity_var: float,
) -> str | None:
    """``implausibility`` of a fix with a position (``x``, ``y``: its own, passed known not None), its
    position and velocity variances given."""
    if not _finite(x, y, fix.vx, fix.vy):
        return "the estimate is not finite"
    return _beyond_bounds(fix, x, y, last, bounds, position_var, velocity_var)


def _beyond_bounds(
    fix: Fix,
    x: float,
    y: float,
    last: _Point | None,
    bounds: tuple[float, float, float],
    position_var: float,
    velocity_var: float,
) -> str | None:
    """``_implausibility`` of a fix whose position and velocity are known finite."""
    max_speed, accel, radius = bounds
    distance = math.hypot(x, y)
    if distance > radius:
        return f"position {distance:.4g} m from the site origin is beyond site_radius_m {radius:g} m"
    vx, vy = fix.vx, fix.vy
    if vx is not None and vy is not None:
        speed = math.hypot(vx, vy)
        if speed > max_speed + SIGMA_ALLOWANCE * math.sqrt(velocity_var):
            return (
                f"speed {speed:.4g} m/s exceeds max_speed_mps {max_speed:g} m/s (beyond the "
                "filter's own velocity uncertainty)"
            )
    if last is None or fix.status == "initialised":
        return None  # a new track (or the first fix): nothing to compare with
    last_t, last_x, last_y, last_vx, last_vy, last_position_var, last_velocity_var = last  # read once
    t = fix.t
    if not t > last_t:
        return None
    dt = t - last_t
    velocity_var = velocity_var + last_velocity_var
    if vx is not None and vy is not None and last_vx is not None and last_vy is not None:
        change = math.hypot(vx - last_vx, vy - last_vy)
        if change > accel * dt + SIGMA_ALLOWANCE * math.sqrt(velocity_var):
            return (
                f"acceleration {change / dt:.4g} m/s^2 over {dt:.4g} s exceeds max_acceleration_mps2 {accel:g} "
                "m/s^2 (beyond the filter's own velocity uncertainty)"
            )
        carried_x = last_x + 0.5 * (last_vx + vx) * dt
        carried_y = last_y + 0.5 * (last_vy + vy) * dt
    else:
        carried_x, carried_y = last_x, last_y
    miss = math.hypot(x - carried_x, y - carried_y)
    spread = position_var + last_position_var + 0.25 * velocity_var * dt * dt
    if miss > max_speed * dt + 0.5 * accel * dt * dt + SIGMA_ALLOWANCE * math.sqrt(max(spread, 0.0)):
        return (
            f"position jumped {miss:.4g} m in {dt:.4g} s away from where the velocities carry the previous fix "
            f"(a displacement at {miss / dt:.4g} m/s beyond max_speed_mps {max_speed:g} m/s, and beyond the filter's "
            "own uncertainty)"
        )
    return None


def _with_indices(fix: Fix, indices: Sequence[int]) -> Fix:
    """A fix of a sub-batch with its measurement indices mapped back to the whole batch's."""
    return dataclasses.replace(
        fix, measurements=[dataclasses.replace(use, index=indices[use.index]) for use in fix.measurements]
    )


class _Judge:
    """Checks a batch's fixes in order and applies the session's divergence policy."""

    def __init__(
        self,
        inner: Pipeline,
        envelope: _Envelope,
        observations: Sequence[Observation],
        environment: Environment,
    ) -> None:
        self.inner = inner
        self.envelope = envelope
        self.options = envelope.options
        self.bounds = _bounds(envelope.options)
        self.observations = observations
        self.environment = environment

    def run(self, fixes: list[Fix] | None, state: bytes) -> tuple[list[Fix], bytes]:
        """The judged fixes and the inner state after them. ``fixes``: the inner pipeline's fixes of the
        whole batch and ``state`` its state after them; None: that run failed (EstimationError) and
        ``state`` is the state before the batch.

        ``queue``: fixes filtered but not judged yet; ``unfiltered``: observations (indices) still to
        filter: after the batch's first reset all of the rest at once, after further resets (or a failed
        run) in chunks of 1, 2, 4, ... epochs, so that the work a further reset throws away is at most
        what was kept since the previous one (a batch diverging at every epoch costs a few plain runs,
        not the square of its length). A chunk that fails is filtered again epoch by epoch; a single
        epoch that fails raises its error."""
        envelope = self.envelope
        envelope.clock_reset = False  # the inner state filters this batch: its clock is set again
        reset = self.options["on_divergence"] == "reset"
        judged: list[Fix] = []
        queue = collections.deque(fixes or ())
        unfiltered: list[int] = [] if fixes is not None else list(range(len(self.observations)))
        chunk: int | None = None if fixes is not None else 1  # epochs per call; None: all that are left
        resets = 0
        while queue or unfiltered:
            if not queue:
                part, rest = _first_epochs(self.observations, unfiltered, chunk)
                try:
                    new, state = self._filter(state, part)
                except EstimationError:
                    if len({self.observations[i].t for i in part}) == 1:
                        raise
                    chunk = 1
                    continue
                unfiltered = rest
                queue.extend(new)
                chunk = None if chunk is None else 2 * chunk
                continue
            fix = queue.popleft()
            reason, point = _judged(fix, envelope.last, self.bounds)
            if reason is None:
                envelope.last = point or envelope.last
                judged.append(fix)
                continue
            if not reset:
                judged.append(
                    dataclasses.replace(
                        fix,
                        status=DIVERGED,
                        integrity="alarm",
                        divergence=f"{reason}; reported only (on_divergence=report): the filter goes on from this "
                        "estimate",
                    )
                )
                envelope.last = point
                continue
            judged.append(
                dataclasses.replace(
                    fix,
                    status=DIVERGED,
                    integrity="alarm",
                    divergence=f"{reason}; the session was reset (on_divergence=reset): it starts again from its "
                    "next measurements; do not use this estimate",
                )
            )
            state = self.inner.create(self.inner.summarise(state).options, None)
            envelope.last = None
            queue.clear()
            unfiltered = [i for i, o in enumerate(self.observations) if o.t > fix.t]
            # A fresh inner state has no clock: until it filters again, the wrapper keeps time monotone.
            envelope.clock_reset = not unfiltered
            resets += 1
            chunk = None if resets == 1 else 1
        return judged, state

    def _filter(self, state: bytes, indices: list[int]) -> tuple[list[Fix], bytes]:
        fixes, state = self.inner.process(state, [self.observations[i] for i in indices], self.environment)
        return [_with_indices(fix, indices) for fix in fixes], state


def _first_epochs(
    observations: Sequence[Observation], indices: list[int], epochs: int | None
) -> tuple[list[int], list[int]]:
    """``indices`` split into the observations of their first ``epochs`` times (all: None) and the rest,
    each in the batch's order."""
    if epochs is None:
        return indices, []
    times = set(sorted({observations[i].t for i in indices})[:epochs])
    return [i for i in indices if observations[i].t in times], [
        i for i in indices if observations[i].t not in times
    ]
