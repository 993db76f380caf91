"""Motion models and their registry: a new model is one module plus one line here."""

from __future__ import annotations

from typing import Any

from edgepos.core.errors import ConfigurationError
from edgepos.core.motion.at import AdaptiveTurn
from edgepos.core.motion.base import MotionModel
from edgepos.core.motion.ca import ConstantAcceleration
from edgepos.core.motion.ct import CoordinatedTurn
from edgepos.core.motion.current_statistical import CurrentStatistical
from edgepos.core.motion.cv import ConstantVelocity
from edgepos.core.motion.singer import Singer
from edgepos.core.parameters import check_parameters

MOTION_MODELS: dict[str, type[MotionModel]] = {
    model.name: model
    for model in (
        ConstantVelocity,
        ConstantAcceleration,
        CoordinatedTurn,
        AdaptiveTurn,
        Singer,
        CurrentStatistical,
    )
}


def make_motion_model(name: str, **params: Any) -> MotionModel:
    """Build a registered motion model by name with keyword parameters (defaults for the rest).

    The parameters are checked against the model's ``parameters`` (names, types and the service's
    bounds, ``core.parameters``): a bad one is a ConfigurationError whose ``parameter`` names it."""
    try:
        cls = MOTION_MODELS[name]
    except KeyError:
        raise ConfigurationError(f"unknown motion model {name!r}; known: {sorted(MOTION_MODELS)}") from None
    params = check_parameters(f"motion model {name!r}", cls.parameters, params)
    try:
        return cls(**params)
    except TypeError as error:
        raise ConfigurationError(f"bad parameters for motion model {name!r}: {error}") from None


__all__ = ["MOTION_MODELS", "MotionModel", "make_motion_model"]
