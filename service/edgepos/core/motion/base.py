"""The motion-model contract shared by every filter.

A motion model acts on a sub-state: the components of the 8-dim state (``core.layout``) it uses,
in full-state order. Filters only ever see these four operations, so any model works in any filter.
"""

from __future__ import annotations

import functools
import math
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np
from scipy.linalg import block_diag, expm

from edgepos.core.errors import ConfigurationError

#: Timestamps are resolved to this step (1 ns) when a discretisation is cached per interval.
DT_RESOLUTION_DECIMALS = 9


class MotionModel(ABC):
    """Discrete-time state transition x_k = f(x_{k-1}, dt) + w, w ~ N(0, Q(x_{k-1}, dt))."""

    #: Registry name, lower case ("cv", "ca", ...).
    name: ClassVar[str]
    #: Full-state indices the model uses, ascending.
    components: ClassVar[tuple[int, ...]]
    #: True when f is linear in the state, so that F P F^T + Q is the exact predicted covariance.
    linear: ClassVar[bool]
    #: True when Q depends on the state (adaptive models); otherwise Q depends on dt only.
    state_dependent_noise: ClassVar[bool] = False

    @property
    def dim(self) -> int:
        return len(self.components)

    @abstractmethod
    def propagate(self, points: np.ndarray, dt: float) -> np.ndarray:
        """Apply f to each row of ``points`` (n, dim); return (n, dim)."""

    @abstractmethod
    def transition_matrix(self, mean: np.ndarray, dt: float) -> np.ndarray:
        """F for a linear model; for a nonlinear one the Jacobian of f at ``mean``."""

    @abstractmethod
    def noise_covariance(self, mean: np.ndarray, dt: float) -> np.ndarray:
        """Q of the step, evaluated at the prior ``mean`` (state-dependent only for adaptive models)."""

    @abstractmethod
    def params(self) -> dict[str, Any]:
        """The model's parameters, enough to rebuild it with ``cls(**params)``."""

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "params": self.params()}


def check_positive(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0.0:
        raise ConfigurationError(f"{name} must be a finite positive number, got {value!r}")
    return value


def check_nonnegative(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value < 0.0:
        raise ConfigurationError(f"{name} must be a finite non-negative number, got {value!r}")
    return value


#: How a model's process noise enters between two epochs (see :func:`discrete_noise`).
NOISE_FORMS = ("discrete", "continuous")


def check_noise_form(value: str) -> str:
    if value not in NOISE_FORMS:
        raise ConfigurationError(f"noise must be one of {NOISE_FORMS}, got {value!r}")
    return value


def discrete_noise(gain: float, order: int, dt: float) -> np.ndarray:
    """Per-axis Q = gain^2 G G^T of piecewise-constant noise (Bar-Shalom, Li, Kirubarajan 2001, 6.3).

    ``order`` 2: [p, v] driven by an acceleration held constant over the interval,
    G = [T^2/2, T] (DWNA). ``order`` 3: [p, v, a] whose acceleration jumps by one draw per
    interval, G = [T^2/2, T, 1] (DWPA). ``gain`` is the standard deviation of that draw (m/s^2):
    the "process-noise gain" of the RSU + IMU paper.
    """
    column = np.array([dt * dt / 2.0, dt, 1.0][:order])
    return gain * gain * np.outer(column, column)


def dt_key(dt: float) -> float:
    """The interval used for discretisation caches: dt rounded to 1 ns."""
    return round(float(dt), DT_RESOLUTION_DECIMALS)


def van_loan(a: np.ndarray, noise_density: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation of dx = A x dt + dw with E[dw dw^T] = noise_density dt.

    Van Loan (1978): expm([[-A, Qc], [0, A^T]] h) holds F^T in its lower-right block and
    F^{-1} Q in its upper-right block. The -A block grows like e^{|A| h}, so the formula is only
    used on a short step h (|A| h <= 1/2), and the interval is then doubled back up with
    F(2h) = F(h)^2, Q(2h) = Q(h) + F(h) Q(h) F(h)^T: every term is positive, nothing cancels.
    """
    n = a.shape[0]
    norm = float(np.max(np.sum(np.abs(a), axis=1))) * dt
    doublings = max(0, math.ceil(math.log2(norm / 0.5))) if norm > 0.5 else 0
    step = dt / 2.0**doublings
    block = np.zeros((2 * n, 2 * n))
    block[:n, :n] = -a
    block[:n, n:] = noise_density
    block[n:, n:] = a.T
    exponential = expm(block * step)
    transition = exponential[n:, n:].T
    noise = transition @ exponential[:n, n:]
    for _ in range(doublings):
        noise = noise + transition @ noise @ transition.T
        transition = transition @ transition
    return transition, 0.5 * (noise + noise.T)


def padded_linear_step(models: tuple[MotionModel, ...], dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Transitions and noises of a bank's models as padded 8x8 matrices, stacked (cached per interval).

    Rows and columns of components a model lacks are zero, so a padded covariance stays zero there.
    A nonlinear model gets the identity and zero noise (its filter predicts it separately), and a
    state-dependent noise is left zero here: the caller adds it per step.
    """
    return _padded_linear_step(models, dt_key(dt))


@functools.lru_cache(maxsize=256)
def _padded_linear_step(models: tuple[MotionModel, ...], dt: float) -> tuple[np.ndarray, np.ndarray]:
    transitions = np.zeros((len(models), 8, 8))
    noises = np.zeros((len(models), 8, 8))
    for b, model in enumerate(models):
        block = np.ix_(model.components, model.components)
        zero = np.zeros(model.dim)
        if not model.linear:
            transitions[b] = np.eye(8)
            continue
        transitions[b][block] = model.transition_matrix(zero, dt)
        if not model.state_dependent_noise:
            noises[b][block] = model.noise_covariance(zero, dt)
    transitions.setflags(write=False)
    noises.setflags(write=False)
    return transitions, noises


class LinearAxisModel(MotionModel):
    """A linear model whose x and y axes follow the same independent continuous-time SDE.

    Subclasses give the per-axis drift matrix and noise density; F and Q are discretised exactly
    (Van Loan) and cached per interval.
    """

    linear: ClassVar[bool] = True

    @abstractmethod
    def axis_drift(self) -> np.ndarray:
        """Continuous-time per-axis drift matrix A."""

    @abstractmethod
    def axis_noise_density(self) -> np.ndarray:
        """Continuous-time per-axis noise spectral density L q L^T."""

    def axis_discrete_noise(self, dt: float) -> np.ndarray | None:
        """Per-axis Q when the model's noise is piecewise constant; None for the continuous form."""
        return None

    def discretise(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return _axis_discretisation(self, dt_key(dt))

    def propagate(self, points: np.ndarray, dt: float) -> np.ndarray:
        transition, _ = self.discretise(dt)
        return points @ transition.T

    def transition_matrix(self, mean: np.ndarray, dt: float) -> np.ndarray:
        return self.discretise(dt)[0]

    def noise_covariance(self, mean: np.ndarray, dt: float) -> np.ndarray:
        return self.discretise(dt)[1]

    def __hash__(self) -> int:
        # Parameters are fixed at construction, so the hash is computed once (it keys the caches).
        try:
            return self._hash
        except AttributeError:
            self._hash: int = hash((type(self).__name__, tuple(sorted(self.params().items()))))
            return self._hash

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and other.params() == self.params()  # type: ignore[attr-defined]


@functools.lru_cache(maxsize=512)
def _axis_discretisation(model: LinearAxisModel, dt: float) -> tuple[np.ndarray, np.ndarray]:
    axis_f, axis_q = van_loan(model.axis_drift(), model.axis_noise_density(), dt)
    discrete = model.axis_discrete_noise(dt)
    if discrete is not None:
        axis_q = discrete
    transition = block_diag(axis_f, axis_f)
    noise = block_diag(axis_q, axis_q)
    transition.setflags(write=False)
    noise.setflags(write=False)
    return transition, noise
