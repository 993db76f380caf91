"""Particle filters over batches of states (bootstrap PF, unscented PF) and the single UKF baseline,
registered by name: a new filter is one module plus one line here."""

from __future__ import annotations

from edgepos.core.particles.base import Cloud, Measurement, StepResult
from edgepos.core.particles.pf import ParticleFilter
from edgepos.core.particles.ukf import UnscentedKalmanFilter
from edgepos.core.particles.upf import UnscentedParticleFilter

PARTICLE_FILTERS = {"pf": ParticleFilter, "upf": UnscentedParticleFilter, "ukf": UnscentedKalmanFilter}
"""Filter name -> class; PF and UPF take ``resample_threshold``."""

__all__ = [
    "PARTICLE_FILTERS",
    "Cloud",
    "Measurement",
    "ParticleFilter",
    "StepResult",
    "UnscentedKalmanFilter",
    "UnscentedParticleFilter",
]
