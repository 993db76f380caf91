"""The ``rsu_imu`` fix of an epoch: the fused output's position, velocity, heading, turn rate and
covariances, the model probabilities and the measurement records, as a ``Fix`` (built without its
generated ``__init__``, which costs a tenth of the Python around an epoch's filter step)."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from edgepos.core import layout
from edgepos.core.errors import NumericalError
from edgepos.core.imm import Gaussian, InteractingMultipleModel
from edgepos.core.integrity import UNAVAILABLE, Protection
from edgepos.pipelines.base import Fix, MeasurementUse

if TYPE_CHECKING:  # the session type only: rsu_imu imports this module
    from edgepos.pipelines.rsu_imu import _SessionState


@functools.lru_cache(maxsize=64)
def fix_layout(components: tuple[int, ...]) -> tuple[tuple[int, ...], int, int, tuple[str, ...]]:
    """For an output over ``components``: the indices of x, y, vx and vy (the kinematic block's order),
    of ax and ay (-1 when the output lacks them), and the components' names."""
    order = list(components)
    kinematic = tuple(order.index(c) for c in (layout.XP, layout.YP, layout.XV, layout.YV))
    ax = order.index(layout.XA) if layout.XA in order else -1
    ay = order.index(layout.YA) if layout.YA in order else -1
    return kinematic, ax, ay, tuple(layout.NAMES[c] for c in order)


#: Every field of a Fix in its order, with its default (None for those ``listed_fix`` always sets).
_FIX_DEFAULTS = {
    f.name: None if f.default is dataclasses.MISSING else f.default for f in dataclasses.fields(Fix)
}


@functools.lru_cache(maxsize=64)
def _fix_fields(components: tuple[int, ...]) -> dict[str, Any]:
    """Every field of a Fix in its order with its default, and the names of an output over
    ``components``: what ``listed_fix`` copies and fills in (never changed itself)."""
    return {**_FIX_DEFAULTS, "state_components": fix_layout(components)[3]}


def epoch_fix(
    t: float,
    status: str,
    output: Gaussian,
    session: _SessionState,
    bank: InteractingMultipleModel,
    uses: dict[int, MeasurementUse],
    nis: float | None,
    dof: int,
    protection: Protection | None = None,
) -> Fix:
    """The fix of an epoch whose fused estimate is ``output`` and model probabilities the session's."""
    components = tuple(output.components)
    state = output.mean.tolist()
    yaw_rate = None
    if not has_acceleration(components):
        yaw_rate = carried_yaw_rate(session, bank)
    probabilities = dict(zip(session.options["models"], session.probabilities.tolist()))
    level, integrity = (None, UNAVAILABLE) if protection is None else (protection.level, protection.state)
    return listed_fix(
        t,
        status,
        components,
        state,
        output.cov.tolist(),
        probabilities,
        uses,
        nis,
        dof,
        level,
        integrity,
        yaw_rate,
    )


def has_acceleration(components: tuple[int, ...]) -> bool:
    """Whether an output over ``components`` gives the turn rate itself (it has both accelerations)."""
    _, ax, ay, _ = fix_layout(components)
    return ax >= 0 and ay >= 0


def listed_fix(
    t: float,
    status: str,
    components: tuple[int, ...],
    state: list[float],
    state_cov: list[list[float]],
    probabilities: dict[str, float],
    uses: dict[int, MeasurementUse],
    nis: float | None,
    dof: int,
    protection_level: float | None,
    integrity: str,
    carried_yaw: float | None,
    blocks: tuple[list[list[float]], list[list[float]]] | None = None,
) -> Fix:
    """The fix of a fused estimate over ``components`` given as Python lists (its mean and its covariance's
    rows) with the model probabilities, its protection level and integrity state (a ``Protection``'s, or
    None and ``UNAVAILABLE`` without the monitor: a run states them without making the object);
    ``carried_yaw`` is the turn rate when the estimate has no acceleration to give it
    (``carried_yaw_rate``). ``blocks``: the covariance's kinematic (x, y, vx, vy) and position blocks as
    lists when the caller has them already (a run makes every epoch's at once)."""
    kinematic, ax, ay, _ = fix_layout(components)
    i_x, i_y, i_vx, i_vy = kinematic
    vx, vy = state[i_vx], state[i_vy]
    yaw_rate = carried_yaw
    if ax >= 0 and ay >= 0:  # the turn rate of the velocity vector from the fused kinematics
        yaw_rate = float((vx * state[ay] - state[ax] * vy) / max(vx * vx + vy * vy, 0.01))
    if blocks is None:
        rows = [state_cov[i] for i in kinematic]
        blocks = (
            [[row[i_x], row[i_y], row[i_vx], row[i_vy]] for row in rows],
            [[rows[0][i_x], rows[0][i_y]], [rows[1][i_x], rows[1][i_y]]],
        )
    # the Fix without its generated __init__: being frozen, that sets each of its 27 fields through
    # object.__setattr__ (about 3 us a fix); its fields set in a copy of their defaults, then given to the
    # object whole. The same object otherwise (equal, its fields in their order, pickled and serialised
    # alike: tests/pipelines/test_pipeline_rsu_imu_process.py compares)
    fields = _fix_fields(components).copy()
    fields["t"] = t
    fields["status"] = status
    fields["x"] = state[i_x]
    fields["y"] = state[i_y]
    fields["vx"] = vx
    fields["vy"] = vy
    fields["speed"] = math.hypot(vx, vy)
    fields["heading"] = math.atan2(vy, vx)
    fields["yaw_rate"] = yaw_rate
    fields["position_cov"] = blocks[1]
    fields["kinematic_cov"] = blocks[0]
    fields["state"] = state
    fields["state_cov"] = state_cov
    fields["model_probabilities"] = probabilities
    fields["nis"] = nis
    fields["nis_dof"] = dof
    fields["measurements"] = [uses[i] for i in sorted(uses)]
    fields["protection_level"] = protection_level
    fields["integrity"] = integrity
    fix = object.__new__(Fix)
    object.__setattr__(fix, "__dict__", fields)
    return fix


def carried_yaw_rate(session: _SessionState, bank: InteractingMultipleModel) -> float | None:
    """The turn rate from the models that carry omega, when the fused output has no acceleration.

    None when no model carries omega, or when those that do have no probability left: their
    probabilities can underflow to exactly 0 when the others explain the measurements far better
    (measured: all six models and a 1e4 m initial position std), and 0/0 is no turn rate."""
    carriers = [j for j, m in enumerate(bank.models) if layout.OMEGA in m.components]
    if not carriers:
        return None
    weights = session.probabilities[carriers]
    total = float(weights.sum())
    if not math.isfinite(total):
        raise NumericalError("model probabilities are not finite")
    if total <= 0.0:
        return None
    return float(np.dot(weights, session.means[carriers, layout.OMEGA]) / total)
