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


#: Every field of a Fix in its order, with its default (None for those ``FixForm.fix`` always sets).
_FIX_DEFAULTS = {
    f.name: None if f.default is dataclasses.MISSING else f.default for f in dataclasses.fields(Fix)
}


@functools.lru_cache(maxsize=64)
def _fix_fields(components: tuple[int, ...]) -> dict[str, Any]:
    """Every field of a Fix in its order with its default, and the names of an output over
    ``components``: what ``FixForm.fix`` copies and fills in (never changed itself)."""
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
    form = fix_form(components)
    state = output.mean.tolist()
    yaw_rate = None
    if not form.turns:
        yaw_rate = carried_yaw_rate(session, bank)
    probabilities = dict(zip(session.options["models"], session.probabilities.tolist()))
    level, integrity = (None, UNAVAILABLE) if protection is None else (protection.level, protection.state)
    state_cov = output.cov.tolist()
    rows = [state_cov[i] for i in form.kinematic]
    i_x, i_y, i_vx, i_vy = form.kinematic
    return form.fix(
        t,
        status,
        state,
        state_cov,
        probabilities,
        [uses[i] for i in sorted(uses)],
        nis,
        dof,
        level,
        integrity,
        yaw_rate,
        [[row[i_x], row[i_y], row[i_vx], row[i_vy]] for row in rows],
        [[rows[0][i_x], rows[0][i_y]], [rows[1][i_x], rows[1][i_y]]],
    )


def has_acceleration(components: tuple[int, ...]) -> bool:
    """Whether an output over ``components`` gives the turn rate itself (it has both accelerations)."""
    _, ax, ay, _ = fix_layout(components)
    return ax >= 0 and ay >= 0


class FixForm:
    """The fixes of fused estimates over one tuple of components: where x, y, vx, vy (``kinematic``) and
    the accelerations are in the estimate, whether it gives the turn rate (``turns``: both accelerations),
    and every field of a Fix with its default and the components' names (``fields``, copied per fix, never
    changed itself). Made once per components (``fix_form``), so that a fix reads them as attributes."""

    __slots__ = ("ax", "ay", "fields", "kinematic", "turns")

    def __init__(self, components: tuple[int, ...]) -> None:
        self.kinematic, self.ax, self.ay, _ = fix_layout(components)
        self.turns = self.ax >= 0 and self.ay >= 0
        self.fields = _fix_fields(components)

    def fix(
        self,
        t: float,
        status: str,
        state: list[float],
        state_cov: list[list[float]],
        probabilities: dict[str, float],
        measurements: list[MeasurementUse],
        nis: float | None,
        dof: int,
        protection_level: float | None,
        integrity: str,
        carried_yaw: float | None,
        kinematic_cov: list[list[float]],
        position_cov: list[list[float]],
    ) -> Fix:
        """The fix of a fused estimate given as Python lists (its mean ``state``, its covariance's rows and
        their kinematic (x, y, vx, vy) and position blocks) with the model probabilities, the epoch's
        measurement records in index order, its protection level and integrity state (a ``Protection``'s,
        or None and ``UNAVAILABLE`` without the monitor: a run states them without making the object);
        ``carried_yaw`` is the turn rate when the estimate has no acceleration to give it
        (``carried_yaw_rate``)."""
        i_x, i_y, i_vx, i_vy = self.kinematic
        vx, vy = state[i_vx], state[i_vy]
        yaw_rate = carried_yaw
        if self.turns:  # the turn rate of the velocity vector from the fused kinematics
            yaw_rate = float((vx * state[self.ay] - state[self.ax] * vy) / max(vx * vx + vy * vy, 0.01))
        # the Fix without its generated __init__: being frozen, that sets each of its 27 fields through
        # object.__setattr__ (about 3 us a fix); its fields set in a copy of their defaults, then given to
        # the object whole. The same object otherwise (equal, its fields in their order, pickled and
        # serialised alike: tests/pipelines/test_pipeline_rsu_imu_process.py compares)
        fields = self.fields.copy()
        fields["t"] = t
        fields["status"] = status
        fields["x"] = state[i_x]
        fields["y"] = state[i_y]
        fields["vx"] = vx
        fields["vy"] = vy
        fields["speed"] = math.hypot(vx, vy)
        fields["heading"] = math.atan2(vy, vx)
        fields["yaw_rate"] = yaw_rate
        fields["position_cov"] = position_cov
        fields["kinematic_cov"] = kinematic_cov
        fields["state"] = state
        fields["state_cov"] = state_cov
        fields["model_probabilities"] = probabilities
        fields["nis"] = nis
        fields["nis_dof"] = dof
        fields["measurements"] = measurements
        fields["protection_level"] = protection_level
        fields["integrity"] = integrity
        fix = object.__new__(Fix)
        object.__setattr__(fix, "__dict__", fields)
        return fix


@functools.lru_cache(maxsize=64)
def fix_form(components: tuple[int, ...]) -> FixForm:
    """The ``FixForm`` of estimates over ``components`` (one per components: a run makes its fixes with it)."""
    return FixForm(components)


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
