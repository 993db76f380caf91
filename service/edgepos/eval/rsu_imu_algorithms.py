"""The algorithms of the RSU + IMU paper's sec. 5 as ``rsu_imu`` pipeline options, with its figures.

Table 2: single-model CKFs (CV, CA, CT, AT, Singer). Table 4: IMM banks of CA, AT and Singer models
over EKF, UKF and CKF, and the 2IMM-CKF (CA and AT interact first). The paper ran one filter per RSU
and averaged the estimates; the pipeline's default stacks all RSUs in one update. Each algorithm
therefore comes twice: ``NAME`` (rsu_handling "joint") and ``NAME/avg`` ("average", the paper's reading).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

AVERAGE_SUFFIX = "/avg"
IMM_MODELS = ("ca", "at", "singer")


@dataclass(frozen=True)
class PaperFigures:
    """One row of the paper's Table 2 or 4: mean position RMSE (m), mean velocity RMSE (m/s), time
    per step (microseconds)."""

    pos_rmse_m: float
    vel_rmse_mps: float
    step_us: float


@dataclass(frozen=True)
class Algorithm:
    """An evaluated configuration: its name, the pipeline options and the paper's figures if any."""

    name: str
    base: str  # the name without the /avg suffix, as in the paper
    group: str  # "single" (Table 2) or "imm" (Table 4)
    handling: str  # rsu_handling option: "joint" or "average"
    options: dict[str, Any]
    paper: PaperFigures | None


#: Single-model CKFs of Table 2: name -> motion model.
SINGLE_MODELS = {"CV-CKF": "cv", "CA-CKF": "ca", "CT-CKF": "ct", "AT-CKF": "at", "Singer-CKF": "singer"}
#: IMM variants of Table 4: name -> (filter, 2IMM priority set; empty = plain IMM).
IMM_VARIANTS = {
    "IMM-EKF": ("ekf", ()),
    "IMM-UKF": ("ukf", ()),
    "IMM-CKF": ("ckf", ()),
    "2IMM-CKF": ("ckf", ("ca", "at")),
}
#: The paper's Tables 2 and 4 (its times are in ms; here microseconds).
PAPER = {
    "CV-CKF": PaperFigures(0.2210, 0.9710, 109.9),
    "CA-CKF": PaperFigures(0.2118, 0.8048, 113.7),
    "CT-CKF": PaperFigures(0.3625, 2.1503, 102.8),
    "AT-CKF": PaperFigures(0.2081, 0.8221, 103.6),
    "Singer-CKF": PaperFigures(0.2036, 0.7882, 112.0),
    "IMM-EKF": PaperFigures(0.1937, 0.7105, 165.1),
    "IMM-UKF": PaperFigures(0.1880, 0.6781, 279.2),
    "IMM-CKF": PaperFigures(0.1832, 0.6614, 350.0),
    "2IMM-CKF": PaperFigures(0.1675, 0.6221, 345.1),
}


def _catalogue() -> dict[str, Algorithm]:
    bases: list[tuple[str, str, dict[str, Any]]] = []
    for name, model in SINGLE_MODELS.items():
        bases.append((name, "single", {"filter": "ckf", "models": [model], "priority": []}))
    for name, (filter_name, priority) in IMM_VARIANTS.items():
        options = {
            "filter": filter_name,
            "models": list(IMM_MODELS),
            "priority": list(priority),
            "transition_diagonal": 0.98,
        }
        bases.append((name, "imm", options))
    catalogue = {}
    for name, group, options in bases:
        for handling, suffix in (("joint", ""), ("average", AVERAGE_SUFFIX)):
            full = name + suffix
            # the evaluation measures integrity too: every algorithm runs the monitor
            options_here = {**options, "rsu_handling": handling, "integrity": True}
            catalogue[full] = Algorithm(full, name, group, handling, options_here, PAPER[name])
    return catalogue


#: Every algorithm the command knows, in table order.
ALGORITHMS: dict[str, Algorithm] = _catalogue()


#: Options that say which algorithm a row is; an override may not change them.
DEFINING_OPTIONS = frozenset({"filter", "models", "priority", "rsu_handling"})


def with_overrides(algorithms: list[Algorithm], overrides: dict[str, Any]) -> list[Algorithm]:
    """The same algorithms with ``overrides`` set on each (a sensitivity run, e.g. another Singer sigma).

    ``model_params`` entries go only to the algorithms whose bank has that model. Raises ValueError for
    an option that would change which algorithm a row is.
    """
    defining = sorted(DEFINING_OPTIONS & overrides.keys())
    if defining:
        raise ValueError(f"--option {', '.join(defining)}: choose algorithms with --algorithms instead")
    changed = []
    for algorithm in algorithms:
        options = {**algorithm.options, **overrides}
        if isinstance(overrides.get("model_params"), dict):
            models = set(algorithm.options["models"])
            options["model_params"] = {m: p for m, p in overrides["model_params"].items() if m in models}
        changed.append(replace(algorithm, options=options))
    return changed


class UnknownAlgorithm(ValueError):
    """An --algorithms entry that names no known algorithm."""


def select_algorithms(spec: str | None) -> list[Algorithm]:
    """The algorithms named in a comma-separated ``spec`` (case-insensitive), in table order; all when
    ``spec`` is None."""
    if spec is None:
        return list(ALGORITHMS.values())
    by_folded = {name.casefold(): name for name in ALGORITHMS}
    wanted, unknown = set(), []
    for item in (part.strip() for part in spec.split(",")):
        if not item:
            continue
        if item.casefold() in by_folded:
            wanted.add(by_folded[item.casefold()])
        else:
            unknown.append(item)
    if unknown:
        names = ", ".join(map(repr, unknown))
        raise UnknownAlgorithm(f"--algorithms: unknown algorithm(s) {names}; known: {', '.join(ALGORITHMS)}")
    if not wanted:
        raise UnknownAlgorithm(f"--algorithms: no algorithm given; known: {', '.join(ALGORITHMS)}")
    return [algorithm for name, algorithm in ALGORITHMS.items() if name in wanted]
