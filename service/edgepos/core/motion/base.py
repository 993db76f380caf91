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
from scipy.linalg import expm

from edgepos.core.errors import ConfigurationError
from edgepos.core.numerics import FloatArray
from edgepos.core.parameters import ParameterSpec

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
    #: The constructor's parameters a client may set by name, with the bounds the service accepts.
    parameters: ClassVar[tuple[ParameterSpec, ...]] = ()

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


#: The parameters several models share (see ``core.parameters``).
Q_PARAMETER = ParameterSpec(
    "q", "process-noise gain, m/s^2 per axis; with noise continuous the spectral density", 1e-6, 100.0
)
NOISE_PARAMETER = ParameterSpec("noise", "how the process noise enters between epochs", choices=NOISE_FORMS)


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


def integrator_chain(order: int, density: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact F and Q of a chain of ``order`` integrators driven by white noise of spectral density
    ``density`` on its last state (CV: order 2, CA: order 3), in closed form.

    F[i, j] = T^(j-i) / (j-i)!; with m = order - 1 - i and n = order - 1 - j the powers of T that
    reach states i and j, Q[i, j] = density T^(m+n+1) / (m! n! (m+n+1)). Every term is a positive
    monomial, so nothing cancels, and it costs a few microseconds where Van Loan costs tens: with
    timestamps that jitter, every interval is new and misses the per-interval caches.
    """
    lag, transition_coefficients, total, noise_coefficients = _chain_tables(order)
    return dt**lag * transition_coefficients, density * dt**total * noise_coefficients


@functools.lru_cache(maxsize=8)
def _chain_tables(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The exponents and coefficients of :func:`integrator_chain`, which depend on the order only."""
    index = np.arange(order)
    lag = np.maximum(index[None, :] - index[:, None], 0)
    factorial = np.array([math.factorial(k) for k in range(2 * order)], dtype=float)
    transition_coefficients = np.where(index[None, :] >= index[:, None], 1.0 / factorial[lag], 0.0)
    powers = order - 1 - index
    total = powers[:, None] + powers[None, :] + 1
    noise_coefficients = 1.0 / (factorial[powers][:, None] * factorial[powers][None, :] * total)
    return lag, transition_coefficients, total, noise_coefficients


def markov_chain(order: int, rate: float, density: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact F and Q of a chain of ``order`` states whose last one is a first-order Markov process,
    d x_last = -rate x_last dt + dw with E[dw^2] = density dt (Singer: order 3, the AT turn rate:
    order 2), in closed form; ``rate`` 0 is :func:`integrator_chain`.

    With z = rate T and phi_m(x) = sum_k x^k / (k+m)!, the column that reaches state i from the last
    is g_i(s) = s^m phi_m(-rate s), m = order - 1 - i: F's last column is g(T) and
    Q = density int_0^T g g^T ds, a power series in z per entry whose coefficients depend on the
    order only. The series is summed where z <= 1/2 (a few dozen terms reach the last bit); a longer
    interval is halved until it is that short, and doubled back with F(2h) = F(h)^2,
    Q(2h) = Q(h) + F(h) Q(h) F(h)^T (positive terms only), as Van Loan's formula is used in
    :func:`van_loan`. Costs microseconds, so intervals that jitter do not need a cache hit.
    """
    if rate == 0.0:
        return integrator_chain(order, density, dt)
    doublings = max(0, math.ceil(math.log2(rate * dt / 0.5))) if rate * dt > 0.5 else 0
    step = dt / 2.0**doublings
    lag, transition_coefficients, total, _ = _chain_tables(order)
    column_series, noise_series = _markov_tables(order)
    powers = (-rate * step) ** np.arange(_MARKOV_TERMS)
    transition = step**lag * transition_coefficients
    reach = order - 1 - np.arange(order)
    transition[:, -1] = step**reach * (column_series @ powers)
    noise = density * step**total * (noise_series @ powers)
    for _ in range(doublings):
        noise = noise + transition @ noise @ transition.T
        transition = transition @ transition
    return transition, 0.5 * (noise + noise.T)


_MARKOV_TERMS = 30


@functools.lru_cache(maxsize=8)
def _markov_tables(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Series coefficients of :func:`markov_chain`: phi_m's for F's last column, (order,  K), and
    sum_{j<=k} 1 / ((j+m)! (k-j+n)!) / (m+n+k+1) for Q[i, j], (order, order, K)."""
    terms = _MARKOV_TERMS
    inverse_factorial = np.array([1.0 / math.factorial(k) for k in range(terms + 2 * order)])
    reach = order - 1 - np.arange(order)
    column = np.array([[inverse_factorial[k + m] for k in range(terms)] for m in reach])
    noise = np.zeros((order, order, terms))
    for i, m in enumerate(reach):
        for j, n in enumerate(reach):
            for k in range(terms):
                product = sum(inverse_factorial[a + m] * inverse_factorial[k - a + n] for a in range(k + 1))
                noise[i, j, k] = product / (m + n + k + 1)
    return column, noise


def two_axes(axis: np.ndarray) -> np.ndarray:
    """The block-diagonal matrix diag(axis, axis) for a model whose x and y axes are alike."""
    n = axis.shape[0]
    out = np.zeros((2 * n, 2 * n))
    out[:n, :n] = axis
    out[n:, n:] = axis
    return out


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

    def axis_exact(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Per-axis F and continuous-form Q over ``dt``: Van Loan unless a subclass has a closed form."""
        return van_loan(self.axis_drift(), self.axis_noise_density(), dt)

    def discretise(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return _axis_discretisation(self, dt_key(dt))

    def propagate(self, points: np.ndarray, dt: float) -> np.ndarray:
        transition, _ = self.discretise(dt)
        propagated: FloatArray = points @ transition.T
        return propagated

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
        return type(other) is type(self) and other.params() == self.params()


@functools.lru_cache(maxsize=512)
def _axis_discretisation(model: LinearAxisModel, dt: float) -> tuple[np.ndarray, np.ndarray]:
    axis_f, axis_q = model.axis_exact(dt)
    discrete = model.axis_discrete_noise(dt)
    if discrete is not None:
        axis_q = discrete
    transition = two_axes(axis_f)
    noise = two_axes(axis_q)
    transition.setflags(write=False)
    noise.setflags(write=False)
    return transition, noise
