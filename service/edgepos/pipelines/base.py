"""The contract between pipelines and the service: state bytes + observations -> fixes + state bytes.

A pipeline turns a batch of validated observations into one fix per epoch (observations sharing a
timestamp). It is pure: the session's state comes in as bytes and the new state goes out as bytes,
so the service can keep sessions in any store and only write the new state when a whole batch
succeeded. Pipelines import the estimation core and nothing from the web layer.
"""

from __future__ import annotations

import itertools
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from edgepos.core.errors import NumericalError
from edgepos.core.observations import Observation

if TYPE_CHECKING:
    from edgepos.gnss.differential import CorrectionTable
    from edgepos.gnss.ephemerides import Ephemerides


@dataclass(frozen=True)
class Rsu:
    """A roadside unit at (x, y) metres in the site frame, with optional per-unit overrides."""

    id: str
    x: float
    y: float
    range_std: float | None = None
    bearing_std: float | None = None
    radius: float | None = None


@dataclass(frozen=True)
class TrackPoint:
    """One published estimate of a vehicle: time (s, that vehicle's session clock), position (m) and
    velocity (m/s) in the site frame, and the 4x4 covariance of [x, y, vx, vy]."""

    t: float
    x: float
    y: float
    vx: float
    vy: float
    cov: tuple[tuple[float, ...], ...]


@dataclass(frozen=True)
class NeighbourTrack:
    """The recent estimates another vehicle's session has published, oldest first.

    Cooperative pipelines read a neighbour's position at a measurement time from this: predicted
    forward from the last point, or taken from the history when the measurement is older."""

    vehicle_id: str
    points: tuple[TrackPoint, ...]


class Environment(Protocol):
    """What a pipeline may look up beyond its own session (the site's RSU registry, ...)."""

    def rsu(self, rsu_id: str) -> Rsu | None: ...

    @property
    def vehicle_id(self) -> str | None:
        """The vehicle whose session is being processed (None outside the service)."""
        ...

    def neighbour(self, vehicle_id: str) -> NeighbourTrack | None:
        """Another vehicle's published track, None when it has no session (or published nothing)."""
        ...

    def ephemerides(self) -> Ephemerides | None:
        """The site's broadcast ephemerides (``PUT /v1/ephemerides``), None when none are loaded."""
        ...

    def site_origin(self) -> tuple[float, float, float] | None:
        """The site frame's WGS-84 origin (latitude rad, longitude rad, ellipsoidal height m), if configured."""
        ...

    def corrections(self) -> CorrectionTable | None:
        """The site reference station's differential pseudorange corrections (gnss/differential.py), None
        when the site has none."""
        ...


@dataclass(frozen=True)
class StaticEnvironment:
    """An environment backed by dicts of RSUs and neighbour tracks: used by evaluation, tests and the
    simulator, and by the service with what it loaded for one batch."""

    rsus: Mapping[str, Rsu] = field(default_factory=dict)
    tracks: Mapping[str, NeighbourTrack] = field(default_factory=dict)
    vehicle_id: str | None = None
    navigation: Ephemerides | None = None
    origin: tuple[float, float, float] | None = None
    differential: CorrectionTable | None = None

    def rsu(self, rsu_id: str) -> Rsu | None:
        return self.rsus.get(rsu_id)

    def neighbour(self, vehicle_id: str) -> NeighbourTrack | None:
        return self.tracks.get(vehicle_id)

    def ephemerides(self) -> Ephemerides | None:
        return self.navigation

    def site_origin(self) -> tuple[float, float, float] | None:
        return self.origin

    def corrections(self) -> CorrectionTable | None:
        return self.differential


@dataclass(frozen=True)
class InitialState:
    """A known starting point: position (m) and velocity (m/s) in the site frame, with 1-sigma."""

    x: float
    y: float
    vx: float
    vy: float
    position_std: float = 1.0
    velocity_std: float = 1.0


@dataclass(frozen=True)
class Problem:
    """One reason a request cannot be applied: which observation (index), which field, and why."""

    index: int | None
    field: str
    reason: str


class PipelineInputError(ValueError):
    """Options or observations a pipeline refuses; carries every problem found, not just the first."""

    def __init__(self, problems: Sequence[Problem]) -> None:
        self.problems = list(problems)
        super().__init__("; ".join(f"[{p.index}] {p.field}: {p.reason}" for p in self.problems))

    def __reduce__(self) -> tuple[type[PipelineInputError], tuple[list[Problem]]]:
        # Pickled with its problems (heavy batches run in worker processes), not as a bare message.
        return (type(self), (self.problems,))


@dataclass(frozen=True)
class MeasurementUse:
    """Whether observation ``index`` of the batch entered the filter, and if not, why. ``doppler_used`` and
    ``doppler_reason`` say the same of a pseudorange's Doppler (None: the observation carries none);
    ``correction_applied`` and ``correction_reason`` whether a differential correction was added to a
    pseudorange and, if not, why (None: the site has no corrections)."""

    index: int
    kind: str
    used: bool
    reason: str | None = None
    doppler_used: bool | None = None
    doppler_reason: str | None = None
    correction_applied: bool | None = None
    correction_reason: str | None = None
    noise_std: float | None = None
    """A pseudorange that entered the update: its noise std (m) there; None otherwise."""
    noise_reason: str | None = None
    """Why ``noise_std`` is what it is: the noise model at its elevation and C/N0, carrier smoothing, and a
    down-weighting by the fault test over time (pipelines/gnss_faults.py)."""


@dataclass(frozen=True)
class Fix:
    """The estimate after one epoch, in the site frame (m, m/s, rad, rad/s).

    ``status``: "initialised" (first fix, from this epoch's measurements or the given initial state),
    "tracking" (measurements were used), "predicted" (no measurement passed: motion model only),
    "uninitialised" (nothing to start from yet; kinematic fields are None), "diverged" (physically
    implausible: see ``divergence``; set by ``pipelines.plausibility``, never published as a track).
    ``latitude``/``longitude`` (rad) and ``height`` (m, ellipsoidal) are WGS-84, set by pipelines that
    estimate a global position (gnss_tight); others leave them None.
    ``kinematic_cov`` is the 4x4 covariance of [x, y, vx, vy]: with the position and velocity it is
    what the service publishes as the vehicle's track for cooperative neighbours (None: not published).
    """

    t: float
    status: str
    x: float | None = None
    y: float | None = None
    vx: float | None = None
    vy: float | None = None
    speed: float | None = None
    heading: float | None = None
    yaw_rate: float | None = None
    position_cov: list[list[float]] | None = None
    kinematic_cov: list[list[float]] | None = None
    state_components: tuple[str, ...] = ()
    state: list[float] | None = None
    state_cov: list[list[float]] | None = None
    model_probabilities: dict[str, float] = field(default_factory=dict)
    nis: float | None = None
    nis_dof: int = 0
    measurements: list[MeasurementUse] = field(default_factory=list)
    latitude: float | None = None
    longitude: float | None = None
    height: float | None = None
    shared: TrackPoint | None = None
    """What to publish for neighbours when it differs from the fix itself: a cooperative pipeline
    shares an estimate its neighbours' ranges did not shape, so that two vehicles do not count each
    other's information twice (None: publish the fix)."""
    revised: bool = False
    """True for a fix of an epoch answered before, filtered again because late measurements arrived
    (``pipelines.lag``): it replaces the earlier fix of the same ``t``."""
    constraints: tuple[str, ...] | None = None
    """Vehicle pseudo-measurements in this epoch's update (gnss_tight: "non-holonomic", "zero-velocity");
    None for pipelines without them."""
    divergence: str | None = None
    """Set with status "diverged" (``pipelines.plausibility``): which physical bound the estimate broke
    and what was done (the session reset, or only reported); None otherwise."""
    protection_level: float | None = None
    """Horizontal protection level (m) at the session's integrity risk (``core.integrity_bank``); None when
    the pipeline cannot bound its error (``integrity`` says so)."""
    integrity: str = "unavailable"
    """"ok" (protection level within the alert limit, no test failed or its RSU excluded), "alarm" (above
    the alert limit, or a fault was detected and could not be excluded, or the fix diverged) or
    "unavailable" (the pipeline has no bound for this fix: not yet initialised, or no integrity
    monitor)."""


@dataclass(frozen=True)
class OptionSpec:
    """One pipeline option as documented by ``GET /v1/pipelines``."""

    name: str
    type: str
    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[Any, ...] | None = None


@dataclass(frozen=True)
class StateSummary:
    """What ``GET /v1/sessions/{id}`` shows of a state without running the filter."""

    initialised: bool
    t: float | None
    epochs: int
    model_probabilities: dict[str, float]
    options: dict[str, Any]


class Pipeline(ABC):
    """A positioning method offered to sessions, registered by ``name``."""

    name: ClassVar[str]
    description: ClassVar[str]
    measurement_kinds: ClassVar[tuple[str, ...]]
    publishes_track: ClassVar[bool] = False
    """Whether the service publishes a session's estimates as its vehicle's track after each batch,
    for other vehicles' cooperative pipelines to range against. Cooperative pipelines set it; for
    the others it would cost two store round trips per batch that nobody reads."""

    smoother: ClassVar[bool] = False
    """Whether :meth:`smooth` is available: the session's track can be served smoothed."""

    def smooth(
        self,
        state: bytes,
        observations: Sequence[Observation],
        environment: Environment,
        lag_s: float | None = None,
    ) -> list[Fix]:
        """Filter ``observations`` from ``state`` as :meth:`process` does, then smooth backwards: one
        smoothed fix per epoch (``lag_s`` None: each with all the data; else with the data up to
        ``t + lag_s``). Only pipelines with ``smoother = True`` override it; callers check that flag."""
        raise TypeError(f"the {self.name} pipeline has no smoother")

    @abstractmethod
    def option_specs(self) -> list[OptionSpec]:
        """Every option with its default, bounds and meaning."""

    @abstractmethod
    def resolve_options(self, options: Mapping[str, Any] | None) -> dict[str, Any]:
        """Validate ``options`` and fill in defaults: the effective configuration.

        Raises :class:`PipelineInputError` naming each bad option (index None, field = option name).
        """

    @abstractmethod
    def create(self, options: Mapping[str, Any], initial: InitialState | None) -> bytes:
        """A new session state for resolved ``options``, started at ``initial`` if given."""

    @abstractmethod
    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        """Run a batch: validate it whole (raising :class:`PipelineInputError`), then filter epoch
        by epoch. The input ``state`` is never modified; the caller stores the returned one.
        Raises ``core.errors.EstimationError`` if a step cannot be computed."""

    @abstractmethod
    def summarise(self, state: bytes) -> StateSummary:
        """The session's state in words and numbers, without filtering."""

    def replayed_observations(
        self, state: bytes, observations: Sequence[Observation] | None
    ) -> list[Observation]:
        """Stored observations that applying ``observations`` would filter again (``pipelines.lag``), or
        with None all that the session keeps: what the caller must look up and budget for beyond the
        batch. A pipeline that keeps no measurements keeps none."""
        return []

    def window_bounds(self, state: bytes) -> tuple[float | None, float | None, dict[str, Any]]:
        """The oldest and newest epoch the session keeps (None: none) and its window options; without a
        lag window only the newest epoch is known."""
        return None, self.summarise(state).t, {}

    def track(self, state: bytes, environment: Environment, smoothed: bool) -> list[Fix]:
        """The estimates of the epochs the session keeps, oldest first (``pipelines.lag``); a pipeline that
        keeps no measurements has none to give."""
        return []


def is_finite_number(value: Any) -> bool:
    """A finite int or float, not a bool (a plain float answered first: the validations' common case)."""
    if type(value) is float:
        return math.isfinite(value)
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


_FIX_NUMBERS = (
    "x",
    "y",
    "vx",
    "vy",
    "speed",
    "heading",
    "yaw_rate",
    "nis",
    "latitude",
    "longitude",
    "height",
)
_FIX_ARRAYS = ("position_cov", "kinematic_cov", "state", "state_cov")
_chain = itertools.chain.from_iterable


def ensure_finite_fixes(fixes: Sequence[Fix]) -> list[Fix]:
    """``fixes`` as a list, after checking that no number in them is NaN or infinite; otherwise raises
    ``core.errors.NumericalError`` naming the epoch and the field, so that the batch is refused (422
    estimation_failed, the session unchanged) instead of answering a non-finite number."""
    for fix in fixes:
        if _finite_sum(fix):
            continue  # the common case: one sum of every number is finite (NaN and infinity propagate)
        bad = _non_finite_field(fix)
        if bad is not None:
            raise NumericalError(f"the estimate at t={fix.t!r} has a non-finite {bad}")
    return list(fixes)


def _finite_sum(fix: Fix) -> bool:
    """Whether the sum of the fix's scalars and covariances is finite: then none of them is NaN or
    infinite. (A sum that is not finite may be an overflow of finite numbers: the field-by-field look
    decides.) Runs for every fix the service answers, so it avoids a call per field."""
    total = fix.t + sum(fix.model_probabilities.values())
    for value in (fix.x, fix.y, fix.vx, fix.vy, fix.speed, fix.heading, fix.yaw_rate, fix.nis):
        if value is not None:
            total += value
    for rows in (fix.position_cov, fix.kinematic_cov, fix.state_cov):
        if rows is not None:
            total += sum(_chain(rows))  # one sum over every row (a sum per row cost a call each)
    if fix.state is not None:
        total += sum(fix.state)
    if fix.latitude is not None or fix.shared is not None:
        return False  # rarer fields: the field-by-field look covers them
    return math.isfinite(total)


def _non_finite_field(fix: Fix) -> str | None:
    """The first field of ``fix`` holding NaN or infinity, or None. Sums first (one float addition per
    number); only a sum that is not finite is looked at element by element (it may just overflow)."""
    if not math.isfinite(fix.t):
        return "t"
    for name in _FIX_NUMBERS:
        value = getattr(fix, name)
        if value is not None and not math.isfinite(value):
            return name
    for name in _FIX_ARRAYS:
        value = getattr(fix, name)
        if value is None:
            continue
        rows = value if value and isinstance(value[0], list) else [value]
        if not math.isfinite(sum(map(sum, rows))) and not all(math.isfinite(v) for row in rows for v in row):
            return name
    if any(not math.isfinite(p) for p in fix.model_probabilities.values()):
        return "model_probabilities"
    if fix.shared is not None:
        point = fix.shared
        values = [point.t, point.x, point.y, point.vx, point.vy, *(v for row in point.cov for v in row)]
        if not all(math.isfinite(v) for v in values):
            return "shared track point"
    return None
