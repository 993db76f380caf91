"""What a batch costs in CPU, per pipeline, before it runs: the bound on work per request.

Every pipeline has a cost model here, registered by pipeline name (a new pipeline = its model class + one
line in ``_MODELS``; importing this module fails when a registered pipeline has none, or when a model's
features lack a calibration constant, so a missing model is never a silent zero). A model is linear in
a few *features* of the batch's shape: per batch (the state's decoding and encoding) and per epoch
(observations sharing ``t``): the measurements of each kind in it, and the options that scale the work
(filter, motion models, particles, RSU handling, ...). The cost is

    MARGIN x (sum over features of CALIBRATION[pipeline][feature] x feature value)

with the constants fitted as the tightest *upper envelope* of measured CPU time (``bench/batch_cost.py
--fit``: a linear programme, every measured batch at or below the line) and MARGIN on top for the run to
run spread, so the prediction is an upper bound of what ``process`` takes on this box, not a mean.

It is cheap (one pass over the observations to count them per epoch; then one evaluation per distinct
epoch shape) and pure: the service calls :func:`batch_cost_s` on the event loop for every batch before
it is queued, and :func:`epoch_cost_s` at session creation with the largest per-epoch counts it accepts
(:data:`MAX_PER_EPOCH`), so that a session whose options could not process even one epoch within the
budget is refused up front.

Not counted: an rsu_imu epoch whose compiled step meets a non-finite number or a missing Cholesky factor
is run again on the numpy reference (a diverging filter; rare), and the plausibility wrapper
(``pipelines.plausibility``, on_divergence="reset") filters again the epochs after a diverged fix, a
batch that diverges at every epoch costing a few plain runs. Both are the exception the budget is not
sized for.

Per-epoch bounds (:data:`MAX_PER_EPOCH`): a batch with more observations of a kind in one epoch than
its bound is refused (see :func:`epoch_bound_violations`). Kinds a pipeline only reads the first of per
epoch (a second gnss_fix, gyro or odometer in v2v_coop / v2x_federated, riss in gnss_tight) cost only
their bookkeeping; they are bounded anyway so that the largest epoch is defined.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from edgepos.core.observations import Observation
from edgepos.pipelines.registry import PIPELINES

DEFAULT_BUDGET_S = 0.050
"""CPU seconds one batch may cost by default (the service's setting overrides it)."""

MARGIN = 1.5
"""Factor over the fitted envelope, for the spread of one batch's CPU time between runs on this box: the
same case's median moved by 1.2x (median over cases) to 1.7x (90th percentile) between three runs, as
other processes' bursts contend for the two cores' caches and execution units."""

# -- calibration ---------------------------------------------------------------------------------
_US = 1e-6
# Seconds of CPU per unit of each feature (written in microseconds): the upper envelope (a linear
# programme: every case at or below it, sum of envelope / measured least) of each case's median thread
# CPU time over three runs of
#   .venv/bin/python bench/batch_cost.py --json run-N.json            (N = 1, 2, 3; ~330 cases, ~4 min each)
#   .venv/bin/python bench/batch_cost.py --from-json run-1.json run-2.json run-3.json
# on this box: 2 vCPUs (AMD EPYC), Python 3.11.7, numpy 2.4.6, numba 0.68.1, OpenBLAS pinned to one thread
# (as edgepos does), EDGEPOS_NUMBA=1; 2026-11-25. Other test suites and benchmarks were running: 1-minute
# load average 8.6, 5.9 and 5.1 (median during each run; up to 10). Thread CPU time excludes waiting
# for the CPU but not the slowdown of sharing it, so the constants are those of a busy box: on an idle
# one the same batches take less.
CALIBRATION: dict[str, dict[str, float]] = {
    "rsu_imu": {
        # Refitted on 2026-11-28 after the one-model averaged bank's batches became one compiled call again
        # (branch pipefive: an alarm with every test passed no longer ends a run; the constants before predicted
        # 3.19 ms for its 20-epoch batches, measured 0.60-0.65): bench/batch_cost.py --only rsu_imu --json (three
        # runs on Debian's Python 3.11.2, load average 2.0-2.8) then --from-json, 133 rows at their median,
        # envelope / measured 1.00-1.81 (median 1.07). The programme puts nothing on the monitor's own
        # constants: it adds 0.08-0.17 ms to a 20- or 10-epoch batch of the grid's paired rows (3:ca,at,singer
        # joint, 4 to 32 RSUs, with and without it), which the filter's constants cover, so an unmonitored
        # batch is predicted as a monitored one: an upper bound all the same.
        "compiled.epoch": 0 * _US,
        "compiled.model": 4.85 * _US,
        "compiled.joint.rsu": 0 * _US,
        "compiled.joint.rsu_model": 0.271 * _US,
        "compiled.joint.rsu2_model": 0.0752 * _US,
        "compiled.average.rsu": 0 * _US,
        "compiled.average.rsu_model": 1.54 * _US,
        "compiled.gyro_model": 5.84 * _US,
        "reference.epoch": 312 * _US,
        "reference.model": 31 * _US,
        "reference.joint.rsu": 0 * _US,
        "reference.joint.rsu_model": 1.48 * _US,
        "reference.joint.rsu2_model": 0.0505 * _US,
        "reference.average.rsu": 97.3 * _US,
        "reference.average.rsu_model": 5.73 * _US,
        "reference.gyro_model": 41.6 * _US,
        "srukf.epoch": 210 * _US,
        "srukf.model": 126 * _US,
        "srukf.joint.rsu": 9.54 * _US,
        "srukf.joint.rsu_model": 9.68 * _US,
        "srukf.joint.rsu2_model": 0.172 * _US,
        "srukf.average.rsu": 155 * _US,
        "srukf.average.rsu_model": 65 * _US,
        "srukf.gyro_model": 70.4 * _US,
        "observation": 2.1 * _US,
        "batch": 113 * _US,
        "integrity.epoch": 0 * _US,
        "integrity.rsu2": 0 * _US,
        "integrity.rsu3": 0 * _US,
    },
    "gnss_tight": {
        # Refitted on 2026-11-27 evening after the epoch's fifth round (the rest of the epoch's Python; the
        # fourth round's constants predicted 6.1 times the measured CPU of a UPF epoch of 40 pseudoranges, past
        # the test's 6), the same way as after the fourth: bench/batch_cost.py --only gnss_tight --json (three
        # runs on Debian's Python 3.11.2, load 1.3-1.5) then --from-json, 203 rows at their median, envelope /
        # measured 1.00-4.00 (median 1.56). The Doppler constants are not the envelope's but the measured
        # increment, the median over the grid's paired cases of (CPU with the Dopplers - without) / Dopplers
        # (UKF 12, PF 32, UPF 32 pairs), added on top, so that a client's Dopplers count at admission.
        "ukf.epoch": 123 * _US,
        "ukf.update": 131 * _US,
        "ukf.pseudorange": 77.9 * _US,
        "ukf.doppler": 7.9 * _US,
        "pf.epoch": 117 * _US,
        "pf.update": 2.53e03 * _US,
        "pf.pseudorange": 0 * _US,
        "pf.doppler": 187 * _US,
        "upf.epoch": 229 * _US,
        "upf.update": 0 * _US,
        "upf.pseudorange": 74.4 * _US,
        "upf.doppler": 15.7 * _US,
        "pf.particle": 0 * _US,
        "pf.particle_update": 8.33 * _US,
        "pf.particle_pseudorange": 0.108 * _US,
        "upf.particle": 0.539 * _US,
        "upf.particle_update": 0.477 * _US,
        "upf.particle_pseudorange": 0 * _US,
        "exclusion_pseudorange": 0.296 * _US,
        "observation": 37.9 * _US,
        "batch": 258 * _US,
        "batch_particle": 0 * _US,
        # options.integrity (pipelines/gnss_integrity.py): the separations at the prediction and the fix's
        # protection level. The monitor is on in every row of the fit; the fit puts its share on the filters'
        # own constants (both of these are 0 now), which a session with the monitor off is over-predicted by,
        # never under-predicted.
        "integrity.epoch": 0 * _US,
        "integrity.pseudorange": 0 * _US,
    },
    "v2v_coop": {
        "gps.epoch": 314
        * _US,  # the Kalman filter on the fixes (07ee333); refitted alone on 2026-11-26, load 0.4
        "gps.range": 0.0 * _US,
        "gps.range2": 0.0 * _US,
        "gps_dr.epoch": 290 * _US,
        "gps_dr.range": 0.0 * _US,
        "gps_dr.range2": 0.0 * _US,
        "ukf.epoch": 828 * _US,
        "ukf.range": 18.3 * _US,
        "ukf.range2": 0.0 * _US,
        "aug_ukf.epoch": 835 * _US,
        "aug_ukf.range": 34.4 * _US,
        "aug_ukf.range2": 0.0 * _US,
        "observation": 10.5 * _US,
        "batch": 247 * _US,
    },
    "v2x_federated": {
        "epoch": 517 * _US,
        "gnss_fix": 0.0 * _US,
        "dead_reckoning": 150 * _US,
        "range_update": 1060 * _US,
        "range": 0.0 * _US,
        "range2": 0.0 * _US,
        "observation": 33.7 * _US,
        "batch": 194 * _US,
    },
}

MAX_PER_EPOCH: dict[str, dict[str, int]] = {
    # RSUs: the nearest max_rsus (option, <= 64) are used, the rest only reported; every gyro is stacked.
    "rsu_imu": {"rsu": 64, "gyro": 4},
    # Three constellations in open sky: about 10 GPS + 15 BeiDou + 10 Galileo in view at most.
    "gnss_tight": {"pseudorange": 40, "riss": 4},
    "v2v_coop": {"gnss_fix": 4, "gyro": 4, "odometer": 4, "v2v_range": 32},
    "v2x_federated": {"gnss_fix": 4, "gyro": 4, "odometer": 4, "rsu_range": 32, "v2v_range": 32},
}
"""Most observations of each kind one epoch may carry, per pipeline."""

DOPPLER = "doppler"
"""A derived count beside the observation kinds: the epoch's pseudoranges that carry a Doppler (each adds a
range-rate row to gnss_tight's update). Bounded through the pseudoranges, not an observation itself."""


# -- the models ----------------------------------------------------------------------------------
class CostModel(ABC):
    """A pipeline's cost: features of the batch and of each epoch, weighted by CALIBRATION[pipeline]."""

    pipeline: ClassVar[str]
    features: ClassVar[tuple[str, ...]]
    """Every feature name the model can return; each needs a calibration constant."""

    def __init__(self) -> None:
        specs = PIPELINES[self.pipeline].option_specs()
        self.defaults = {spec.name: spec.default for spec in specs}
        self.coefficients = CALIBRATION[self.pipeline]
        self.bounds = MAX_PER_EPOCH[self.pipeline]

    def options(self, options: Mapping[str, Any] | None) -> Mapping[str, Any]:
        """The options with defaults for those not given (resolved options pass through)."""
        if options is None:
            return self.defaults
        if self.defaults.keys() <= options.keys():
            return options
        return {**self.defaults, **options}

    @abstractmethod
    def batch_features(self, options: Mapping[str, Any]) -> dict[str, float]:
        """Features paid once per batch (decoding and encoding the state, ...)."""

    @abstractmethod
    def epoch_features(self, options: Mapping[str, Any], counts: Mapping[str, int]) -> dict[str, float]:
        """Features of one epoch with ``counts`` observations per kind."""

    def weigh(self, features: Mapping[str, float]) -> float:
        coefficients = self.coefficients
        return sum(coefficients[name] * value for name, value in features.items() if value)


def _observations(counts: Mapping[str, int]) -> int:
    return sum(count for kind, count in counts.items() if kind != DOPPLER)


class RsuImuCost(CostModel):
    """Per epoch: the bank's prediction and update, per model, on the compiled kernels when they cover
    the filter and every model, else on the numpy reference (several times dearer; the square-root UKF
    dearer still, so it has constants of its own). The update grows with the RSUs used (the nearest
    ``max_rsus``; joint: one stacked update, whose cost grows faster than linearly; average: one update
    per RSU) and with the gyros (all stacked)."""

    pipeline = "rsu_imu"
    PATHS = ("compiled", "reference", "srukf")
    REFERENCE_PATH: ClassVar[dict[str, str]] = {
        "ekf": "reference",
        "ukf": "reference",
        "ckf": "reference",
        "srukf": "srukf",
    }
    """The constants a filter takes off the compiled kernels; every filter of ``core.filters.FILTERS`` needs
    an entry (checked on import)."""
    features = tuple(
        f"{path}.{name}"
        for path in PATHS
        for name in (
            "epoch",
            "model",
            "joint.rsu",
            "joint.rsu_model",
            "joint.rsu2_model",
            "average.rsu",
            "average.rsu_model",
            "gyro_model",
        )
    ) + ("observation", "batch", "integrity.epoch", "integrity.rsu2", "integrity.rsu3")

    def __init__(self) -> None:
        super().__init__()
        from edgepos.core.compiled import _filter_kind, _motion_kind
        from edgepos.core.filters import FILTERS, make_filter
        from edgepos.core.motion import MOTION_MODELS, make_motion_model

        unknown = sorted(set(FILTERS) - set(self.REFERENCE_PATH))
        if unknown:
            raise RuntimeError(f"rsu_imu cost model: filters without constants: {unknown}")
        self.compiled_filters = frozenset(n for n in FILTERS if _filter_kind(make_filter(n)) is not None)
        self.compiled_models = frozenset(
            n for n in MOTION_MODELS if _motion_kind(make_motion_model(n)) is not None
        )

    def path(self, options: Mapping[str, Any]) -> str:
        """Which constants apply: the compiled kernels' when they cover the bank and are enabled."""
        from edgepos.core.compiled import compiled_enabled

        name = options["filter"]
        covered = name in self.compiled_filters and all(
            model in self.compiled_models for model in options["models"]
        )
        return "compiled" if covered and compiled_enabled() else self.REFERENCE_PATH[name]

    def batch_features(self, options: Mapping[str, Any]) -> dict[str, float]:
        return {"batch": 1.0}

    def epoch_features(self, options: Mapping[str, Any], counts: Mapping[str, int]) -> dict[str, float]:
        path = self.path(options)
        models = len(options["models"])
        rsus = min(counts.get("rsu", 0), int(options["max_rsus"]))
        gyros = counts.get("gyro", 0)
        handling = "average" if options["rsu_handling"] == "average" else "joint"
        features = {
            f"{path}.epoch": 1.0,
            f"{path}.model": models,
            f"{path}.{handling}.rsu": rsus,
            f"{path}.{handling}.rsu_model": rsus * models,
            f"{path}.gyro_model": gyros * models,
            "observation": _observations(counts),
        }
        if handling == "joint":
            features[f"{path}.joint.rsu2_model"] = rsus * rsus * models
        if options.get("integrity"):
            features.update({"integrity.epoch": 1.0, "integrity.rsu2": rsus**2, "integrity.rsu3": rsus**3})
        return features


class GnssTightCost(CostModel):
    """Per epoch: the satellites' orbits and corrections, the snapshot test (each exclusion a least-squares
    solve; ``max_exclusions`` of them at worst) and the filter step. The particle filters cost per
    particle, and per particle and pseudorange at an update (the UPF runs a UKF update per particle); the
    PF's progressive correction is taken at its worst, eight likelihood stages. RISS-only epochs
    propagate the particles. Per batch: decoding and encoding the cloud. A Doppler (with options.use_doppler)
    is one more row of the same stacked update, with a cost of its own per filter (``doppler``: a range
    rate's row costs less than a pseudorange's, which also goes through the screens and RAIM), and counts
    as a row in the particles' per-row cost; the snapshot test's exclusions see only the pseudoranges."""

    pipeline = "gnss_tight"
    features = (
        tuple(
            f"{f}.{name}"
            for f in ("ukf", "pf", "upf")
            for name in ("epoch", "update", "pseudorange", "doppler")
        )
        + tuple(
            f"{f}.{name}"
            for f in ("pf", "upf")
            for name in ("particle", "particle_update", "particle_pseudorange")
        )
        + ("exclusion_pseudorange", "observation", "batch", "batch_particle")
        + ("integrity.epoch", "integrity.pseudorange")
    )

    def batch_features(self, options: Mapping[str, Any]) -> dict[str, float]:
        particles = 1 if options["filter"] == "ukf" else int(options["particles"])
        return {"batch": 1.0, "batch_particle": particles}

    def epoch_features(self, options: Mapping[str, Any], counts: Mapping[str, int]) -> dict[str, float]:
        name = options["filter"]
        pseudoranges = counts.get("pseudorange", 0)
        dopplers = counts.get(DOPPLER, 0) if options.get("use_doppler", True) else 0
        rows = pseudoranges + dopplers
        features = {
            f"{name}.epoch": 1.0,
            f"{name}.update": 1.0 if rows else 0.0,
            f"{name}.pseudorange": pseudoranges,
            f"{name}.doppler": dopplers,
            "exclusion_pseudorange": int(options["max_exclusions"]) * pseudoranges,
            "observation": _observations(counts),
        }
        if options.get("integrity", True) and pseudoranges:
            features.update({"integrity.epoch": 1.0, "integrity.pseudorange": pseudoranges})
        if name != "ukf":
            particles = int(options["particles"])
            features[f"{name}.particle"] = particles
            if rows:
                features[f"{name}.particle_update"] = particles
                features[f"{name}.particle_pseudorange"] = particles * rows
        return features


class V2vCoopCost(CostModel):
    """Per epoch: the method's filters (the cooperative ones run two: the fix's and the shared one); per
    V2V range a neighbour lookup and the range update (the augmented UKF's state grows by two per
    range, so its update grows faster than linearly)."""

    pipeline = "v2v_coop"
    features = tuple(
        f"{method}.{name}"
        for method in ("gps", "gps_dr", "ukf", "aug_ukf")
        for name in ("epoch", "range", "range2")
    ) + ("observation", "batch")

    def batch_features(self, options: Mapping[str, Any]) -> dict[str, float]:
        return {"batch": 1.0}

    def epoch_features(self, options: Mapping[str, Any], counts: Mapping[str, int]) -> dict[str, float]:
        method = options["method"]
        ranges = counts.get("v2v_range", 0)
        return {
            f"{method}.epoch": 1.0,
            f"{method}.range": ranges,
            f"{method}.range2": ranges * ranges,
            "observation": _observations(counts),
        }


class V2xFederatedCost(CostModel):
    """Per epoch: three sub-filter predictions (current-statistical model) and the fusion; the GNSS
    update when a fix came, the DR update when a gyro or odometer reading came, the V2X update with
    every RSU and V2V range (a neighbour lookup each)."""

    pipeline = "v2x_federated"
    features = (
        "epoch",
        "gnss_fix",
        "dead_reckoning",
        "range_update",
        "range",
        "range2",
        "observation",
        "batch",
    )

    def batch_features(self, options: Mapping[str, Any]) -> dict[str, float]:
        return {"batch": 1.0}

    def epoch_features(self, options: Mapping[str, Any], counts: Mapping[str, int]) -> dict[str, float]:
        ranges = counts.get("rsu_range", 0) + counts.get("v2v_range", 0)
        return {
            "epoch": 1.0,
            "gnss_fix": 1.0 if counts.get("gnss_fix") else 0.0,
            "dead_reckoning": 1.0 if counts.get("gyro") or counts.get("odometer") else 0.0,
            "range_update": 1.0 if ranges else 0.0,
            "range": ranges,
            "range2": ranges * ranges,
            "observation": _observations(counts),
        }


_MODELS: dict[str, CostModel] = {
    model.pipeline: model for model in (RsuImuCost(), GnssTightCost(), V2vCoopCost(), V2xFederatedCost())
}


def _check_registry() -> None:
    missing = sorted(set(PIPELINES) - set(_MODELS))
    if missing:
        raise RuntimeError(f"pipelines without a cost model in edgepos.pipelines.cost: {missing}")
    for name, model in _MODELS.items():
        uncalibrated = sorted(set(model.features) - set(model.coefficients))
        if uncalibrated:
            raise RuntimeError(f"cost model {name}: features without a CALIBRATION constant: {uncalibrated}")
        if name not in MAX_PER_EPOCH:
            raise RuntimeError(f"cost model {name}: no MAX_PER_EPOCH bounds")


_check_registry()


def cost_model(pipeline_name: str) -> CostModel:
    """The registered cost model of ``pipeline_name``; KeyError if there is none."""
    return _MODELS[pipeline_name]


# -- batches -------------------------------------------------------------------------------------
def _counts_by_time(observations: Iterable[Observation]) -> dict[float, dict[str, int]]:
    """Observations per kind of each epoch, by the epoch's ``t``, in order of first appearance."""
    by_time: dict[float, dict[str, int]] = {}
    for observation in observations:
        counts = by_time.get(observation.t)
        if counts is None:
            counts = by_time[observation.t] = {}
        kind = observation.kind
        counts[kind] = counts.get(kind, 0) + 1
        if getattr(observation, "doppler_hz", None) is not None:
            counts[DOPPLER] = counts.get(DOPPLER, 0) + 1
    return by_time


def epoch_counts(observations: Iterable[Observation]) -> list[dict[str, int]]:
    """Observations per kind of each epoch (distinct ``t``), in order of first appearance."""
    return list(_counts_by_time(observations).values())


def batch_features(
    pipeline_name: str, options: Mapping[str, Any] | None, counts: Sequence[Mapping[str, int]]
) -> dict[str, float]:
    """The summed features of a batch whose epochs have ``counts`` (before calibration and margin)."""
    model = _MODELS[pipeline_name]
    resolved = model.options(options)
    total = dict(model.batch_features(resolved))
    for shape, repeats in _shapes(counts).items():
        for name, value in model.epoch_features(resolved, dict(shape)).items():
            total[name] = total.get(name, 0.0) + repeats * value
    return total


def batch_cost_s(
    pipeline_name: str, options: Mapping[str, Any] | None, observations: Sequence[Observation]
) -> float:
    """Predicted CPU seconds of ``process`` for this batch on this box: an upper bound (see module doc).
    ``options``: the session's (resolved) options; missing ones take their defaults."""
    # Epochs keyed by their kinds in arrival order: epochs of one shape usually share a key, and the
    # model is evaluated once per key (about 0.2 us per observation in all).
    kinds_by_time: dict[float, list[str]] = {}
    for observation in observations:
        kinds = kinds_by_time.get(observation.t)
        if kinds is None:
            kinds = kinds_by_time[observation.t] = []
        kinds.append(observation.kind)
        if getattr(observation, "doppler_hz", None) is not None:
            kinds.append(DOPPLER)
    keys: dict[tuple[str, ...], int] = {}
    for kinds in kinds_by_time.values():
        key = tuple(kinds)
        keys[key] = keys.get(key, 0) + 1
    model = _MODELS[pipeline_name]
    resolved = model.options(options)
    total = model.weigh(model.batch_features(resolved))
    for key, repeats in keys.items():
        counts: dict[str, int] = {}
        for kind in key:
            counts[kind] = counts.get(kind, 0) + 1
        total += repeats * model.weigh(model.epoch_features(resolved, counts))
    return MARGIN * total


def batch_cost_from_counts_s(
    pipeline_name: str, options: Mapping[str, Any] | None, counts: Sequence[Mapping[str, int]]
) -> float:
    """:func:`batch_cost_s` from the batch's :func:`epoch_counts` (when the caller has them already)."""
    return _cost_of_shapes_s(pipeline_name, options, _shapes(counts))


def _cost_of_shapes_s(
    pipeline_name: str, options: Mapping[str, Any] | None, shapes: Mapping[tuple[tuple[str, int], ...], int]
) -> float:
    """The predicted CPU seconds of a batch whose epochs have these shapes (sorted counts -> epochs)."""
    model = _MODELS[pipeline_name]
    resolved = model.options(options)
    total = model.weigh(model.batch_features(resolved))
    for shape, repeats in shapes.items():
        total += repeats * model.weigh(model.epoch_features(resolved, dict(shape)))
    return MARGIN * total


def epoch_cost_s(
    pipeline_name: str,
    options: Mapping[str, Any] | None,
    measurements_per_epoch: Mapping[str, int] | None = None,
) -> float:
    """Predicted CPU seconds of a batch of one epoch with ``measurements_per_epoch`` (default: the
    largest counts the service accepts, :data:`MAX_PER_EPOCH`), for the check at session creation."""
    counts = MAX_PER_EPOCH[pipeline_name] if measurements_per_epoch is None else measurements_per_epoch
    return batch_cost_from_counts_s(pipeline_name, options, [counts])


def _shapes(counts: Sequence[Mapping[str, int]]) -> dict[tuple[tuple[str, int], ...], int]:
    shapes: dict[tuple[tuple[str, int], ...], int] = {}
    for epoch in counts:
        key = tuple(sorted(epoch.items()))
        shapes[key] = shapes.get(key, 0) + 1
    return shapes


@dataclass(frozen=True)
class EpochBoundViolation:
    """An epoch (time ``t``) with more observations of ``kind`` than the pipeline accepts per epoch."""

    t: float
    kind: str
    count: int
    bound: int

    @property
    def reason(self) -> str:
        return (
            f"{self.count} {self.kind} observations at t={self.t!r}: at most {self.bound} per epoch "
            "(each one adds filter work; the bound keeps one epoch within the CPU budget)"
        )


def epoch_bound_violations(
    pipeline_name: str, observations: Iterable[Observation]
) -> list[EpochBoundViolation]:
    """Every (epoch, kind) whose count exceeds :data:`MAX_PER_EPOCH`; empty when the batch is within."""
    return _violations(pipeline_name, _counts_by_time(observations))


def _violations(pipeline_name: str, by_time: Mapping[float, Mapping[str, int]]) -> list[EpochBoundViolation]:
    bounds = MAX_PER_EPOCH[pipeline_name]
    return [
        EpochBoundViolation(t, kind, count, bounds[kind])
        for t, counts in by_time.items()
        for kind, count in counts.items()
        if kind in bounds and count > bounds[kind]
    ]


def admit(
    pipeline_name: str, options: Mapping[str, Any] | None, observations: Iterable[Observation]
) -> tuple[float, list[EpochBoundViolation]]:
    """:func:`batch_cost_s` and :func:`epoch_bound_violations` in one pass over the batch: what the service
    computes for every batch on its event loop before queueing it."""
    # One pass lists each epoch's kinds in arrival order (a pseudorange's Doppler right after it, as
    # _counts_by_time counts it; only pseudoranges carry ``doppler_hz``). Epochs listing the same kinds
    # share one count, its bound check and its shape, so the model is evaluated once per shape: the same
    # shapes, repeats, order and sums as batch_cost_from_counts_s over epoch_counts, for a third of the CPU.
    kinds_by_time: dict[float, list[str]] = {}
    for observation in observations:
        kind = observation.kind
        kinds = kinds_by_time.get(observation.t)
        if kinds is None:
            kinds = kinds_by_time[observation.t] = [kind]
        else:
            kinds.append(kind)
        if kind == "pseudorange" and getattr(observation, "doppler_hz", None) is not None:
            kinds.append(DOPPLER)
    bounds = MAX_PER_EPOCH[pipeline_name]
    by_kinds: dict[tuple[str, ...], tuple[dict[str, int], bool, tuple[tuple[str, int], ...]]] = {}
    shapes: dict[tuple[tuple[str, int], ...], int] = {}
    violations: list[EpochBoundViolation] = []
    for t, kinds in kinds_by_time.items():
        key = tuple(kinds)
        known = by_kinds.get(key)
        if known is None:
            counts: dict[str, int] = {}
            for kind in key:
                counts[kind] = counts.get(kind, 0) + 1
            over = any(kind in bounds and count > bounds[kind] for kind, count in counts.items())
            known = by_kinds[key] = (counts, over, tuple(sorted(counts.items())))
        counts, over, shape = known
        if over:
            violations.extend(
                EpochBoundViolation(t, kind, count, bounds[kind])
                for kind, count in counts.items()
                if kind in bounds and count > bounds[kind]
            )
        shapes[shape] = shapes.get(shape, 0) + 1
    return _cost_of_shapes_s(pipeline_name, options, shapes), violations


def max_particles(
    filter_name: str,
    budget_s: float = DEFAULT_BUDGET_S,
    pseudoranges: int | None = None,
    options: Mapping[str, Any] | None = None,
) -> int:
    """The most particles for which one epoch with ``pseudoranges`` (default: the most accepted per epoch)
    fits ``budget_s`` with filter ``filter_name`` ("pf" or "upf") and the other ``options`` (default:
    the defaults; ``max_exclusions`` matters a little); 0 if not even one particle does."""
    prs = MAX_PER_EPOCH["gnss_tight"]["pseudorange"] if pseudoranges is None else pseudoranges
    counts = {"pseudorange": prs, "riss": MAX_PER_EPOCH["gnss_tight"]["riss"]}
    base = dict(options or {})

    def cost(n: int) -> float:
        return epoch_cost_s("gnss_tight", {**base, "filter": filter_name, "particles": n}, counts)

    if cost(1) > budget_s:
        return 0
    low, high = 1, 2
    while cost(high) <= budget_s:
        low, high = high, high * 2
        if high > 10**9:  # the model grows with the particles; this would be a calibration error
            raise RuntimeError(f"gnss_tight cost model: {filter_name} particles cost nothing")
    while high - low > 1:
        middle = (low + high) // 2
        if cost(middle) <= budget_s:
            low = middle
        else:
            high = middle
    return low


def budget_fits(
    pipeline_name: str, options: Mapping[str, Any] | None, budget_s: float = DEFAULT_BUDGET_S
) -> bool:
    """Whether one epoch at the largest accepted counts fits ``budget_s`` (the session-creation check)."""
    return epoch_cost_s(pipeline_name, options) <= budget_s


PARTICLES_WITHIN_DEFAULT_BUDGET: dict[str, int] = {name: max_particles(name) for name in ("pf", "upf")}
"""Per particle filter, the most particles for which one epoch with the most pseudoranges accepted per
epoch fits :data:`DEFAULT_BUDGET_S` (the bound of gnss_tight's ``particles`` option follows the UPF's)."""
