"""Compiled (numba) F and Q of a whole bank's motion models for one interval, in one call.

The compiled bank step (``core.compiled``) needs every model's padded 8x8 transition F and process
noise Q before each prediction. The Python closed forms (``core.motion``) cost about 90 µs per bank
and interval, and with clocks that jitter by a few milliseconds every interval is new, so their
per-interval caches never hit. These loops evaluate the same closed forms, term for term and in the
same order, for the models the compiled kernels cover, and agree with them to rounding (the tests
hold them to 1e-13 relative, entry by entry):

- ``CV``, ``CA``: :func:`~edgepos.core.motion.base.integrator_chain` of order 2 or 3 per axis, with
  Q from :func:`~edgepos.core.motion.base.discrete_noise` when the noise form is "discrete";
- ``CT``: ``turn_matrix`` and ``turn_noise`` of ``core.motion.turn``;
- ``AT``: what ``CompiledBankStepper`` takes of the adaptive turn: F zero but for the turn-rate
  block F_omega of :func:`~edgepos.core.motion.base.markov_chain` (order 2; the kinematics follow
  the state's own omega in the prediction kernel) and Q = diag(turn_noise, Q_omega);
- ``SINGER``: :func:`~edgepos.core.motion.base.markov_chain` of order 3 per axis.

Each model is a row of ``params`` (``PARAMETER_COUNT`` floats), packed once by the caller:
``CV``/``CA``: (q, noise form); ``CT``: (q, noise form, omega); ``AT``: (q, noise form, beta,
2 beta eta^2); ``SINGER``: (alpha, 2 alpha sigma^2). Noise form ``DISCRETE`` or ``CONTINUOUS``; the
driving densities are computed by the caller exactly as the models compute them. A model of kind
``UNCOVERED`` gets zero F and Q here: the caller fills it from the Python reference.
"""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.kernels_base import IntArray, _jit
from edgepos.core.motion.base import _MARKOV_TERMS, _chain_tables, _markov_tables
from edgepos.core.numerics import FloatArray

UNCOVERED = -1
CV = 0
CA = 1
CT = 2
AT = 3
SINGER = 4

DISCRETE = 0.0
CONTINUOUS = 1.0

#: Floats per model in ``params``.
PARAMETER_COUNT = 4

#: Where a model's x and y axes sit in the padded state: CV's [p, v], the others' [p, v, a].
_X_AXIS, _Y_AXIS = 0, 3


def _padded_tables() -> tuple[FloatArray, ...]:
    """The reference's series coefficients for orders 2 and 3, zero-padded to 3 states, indexed by
    order - 2: integrator lags and F coefficients, Q exponents and coefficients; Markov F-column and
    Q series (the same numbers :func:`~edgepos.core.motion.base.markov_chain` uses)."""
    order_count = 2
    lags = np.zeros((order_count, 3, 3))
    transition_coefficients = np.zeros((order_count, 3, 3))
    totals = np.zeros((order_count, 3, 3))
    noise_coefficients = np.zeros((order_count, 3, 3))
    column_series = np.zeros((order_count, 3, _MARKOV_TERMS))
    noise_series = np.zeros((order_count, 3, 3, _MARKOV_TERMS))
    for index in range(order_count):
        order = index + 2
        lag, transition, total, noise = _chain_tables(order)
        lags[index, :order, :order] = lag
        transition_coefficients[index, :order, :order] = transition
        totals[index, :order, :order] = total
        noise_coefficients[index, :order, :order] = noise
        column, series = _markov_tables(order)
        column_series[index, :order] = column
        noise_series[index, :order, :order] = series
    return lags, transition_coefficients, totals, noise_coefficients, column_series, noise_series


(
    _LAGS,
    _TRANSITION_COEFFICIENTS,
    _TOTALS,
    _NOISE_COEFFICIENTS,
    _COLUMN_SERIES,
    _NOISE_SERIES,
) = _padded_tables()


@_jit
def _power(x: float, exponent: float) -> float:
    """x ** exponent for a small whole ``exponent`` (a float from the tables) by repeated products:
    within a few ulps of the reference's ``pow``, at a fraction of its cost."""
    out = 1.0
    for _ in range(int(exponent)):
        out *= x
    return out


@_jit
def _integrator_chain(order: int, density: float, dt: float, f: FloatArray, q: FloatArray) -> None:
    """``integrator_chain(order, density, dt)`` into f[:order, :order] and q[:order, :order]."""
    table = order - 2
    for i in range(order):
        for j in range(order):
            f[i, j] = _power(dt, _LAGS[table, i, j]) * _TRANSITION_COEFFICIENTS[table, i, j]
            q[i, j] = density * _power(dt, _TOTALS[table, i, j]) * _NOISE_COEFFICIENTS[table, i, j]


@_jit
def _markov_chain(order: int, rate: float, density: float, dt: float, f: FloatArray, q: FloatArray) -> None:
    """``markov_chain(order, rate, density, dt)`` into f and q: the series on the interval halved until
    rate h <= 1/2, then doubled back as the reference does; rate 0 is the integrator chain."""
    if rate == 0.0:
        _integrator_chain(order, density, dt, f, q)
        return
    table = order - 2
    doublings = 0
    if rate * dt > 0.5:
        doublings = max(0, math.ceil(math.log2(rate * dt / 0.5)))
    step = dt / 2.0**doublings
    terms = _MARKOV_TERMS
    powers = np.empty(terms)
    base = -rate * step
    powers[0] = 1.0
    for k in range(1, terms):
        powers[k] = powers[k - 1] * base
    last = order - 1
    for i in range(order):
        for j in range(order):
            f[i, j] = _power(step, _LAGS[table, i, j]) * _TRANSITION_COEFFICIENTS[table, i, j]
        column = 0.0
        for k in range(terms):
            column += _COLUMN_SERIES[table, i, k] * powers[k]
        f[i, last] = _power(step, last - i) * column
        for j in range(order):
            series = 0.0
            for k in range(terms):
                series += _NOISE_SERIES[table, i, j, k] * powers[k]
            q[i, j] = density * _power(step, _TOTALS[table, i, j]) * series
    temp = np.empty((order, order))
    for _ in range(doublings):
        # Q(2h) = Q(h) + (F Q) F^T, then F(2h) = F F, evaluated in the reference's order.
        for i in range(order):
            for j in range(order):
                total = 0.0
                for k in range(order):
                    total += f[i, k] * q[k, j]
                temp[i, j] = total
        for i in range(order):
            for j in range(order):
                total = 0.0
                for k in range(order):
                    total += temp[i, k] * f[j, k]
                q[i, j] = q[i, j] + total
        for i in range(order):
            for j in range(order):
                total = 0.0
                for k in range(order):
                    total += f[i, k] * f[k, j]
                temp[i, j] = total
        for i in range(order):
            for j in range(order):
                f[i, j] = temp[i, j]
    for i in range(order):
        for j in range(i + 1, order):
            value = 0.5 * (q[i, j] + q[j, i])
            q[i, j] = value
            q[j, i] = value


@_jit
def _discrete_noise(order: int, gain: float, dt: float, q: FloatArray) -> None:
    """``discrete_noise(gain, order, dt)``: gain^2 G G^T with G = [T^2/2, T, 1][:order]."""
    column = (dt * dt / 2.0, dt, 1.0)
    square = gain * gain
    for i in range(order):
        for j in range(order):
            q[i, j] = square * (column[i] * column[j])


@_jit
def _sinc(x: float) -> float:
    """numpy's sinc: sin(pi x) / (pi x), exactly 1 at 0."""
    if x == 0.0:
        return 1.0
    y = math.pi * x
    return math.sin(y) / y


@_jit
def _turn_matrix(omega: float, dt: float, out: FloatArray) -> None:
    """``turn_matrix(omega, dt)`` into out[:6, :6] (the rest of those rows untouched)."""
    angle = omega * dt
    half_sinc = _sinc(angle / (2.0 * math.pi))
    sin = math.sin(angle)
    cos = math.cos(angle)
    sin_over = dt * _sinc(angle / math.pi)
    one_minus_cos_over = 0.5 * angle * dt * half_sinc * half_sinc
    for i in range(6):
        for j in range(6):
            out[i, j] = 0.0
    out[0, 0] = 1.0
    out[0, 1] = sin_over
    out[0, 4] = -one_minus_cos_over
    out[1, 1] = cos
    out[1, 4] = -sin
    out[2, 1] = -omega * sin
    out[2, 4] = -omega * cos
    out[3, 1] = one_minus_cos_over
    out[3, 3] = 1.0
    out[3, 4] = sin_over
    out[4, 1] = sin
    out[4, 4] = cos
    out[5, 1] = omega * cos
    out[5, 4] = -omega * sin


@_jit
def _turn_noise(q: float, continuous: bool, dt: float, out: FloatArray, axis: FloatArray) -> None:
    """``turn_noise(q, form, dt)`` into out[:6, :6] (two axes of ``axis``, a 3x3 scratch)."""
    if continuous:
        half_square = dt * dt / 2.0
        axis[0, 0] = q * (dt * dt * dt / 3.0)
        axis[0, 1] = q * half_square
        axis[0, 2] = 0.0
        axis[1, 0] = q * half_square
        axis[1, 1] = q * dt
        axis[1, 2] = 0.0
        axis[2, 0] = 0.0
        axis[2, 1] = 0.0
        axis[2, 2] = q * dt
    else:
        _discrete_noise(3, q, dt, axis)
    _place_axes(axis, 3, out)


@_jit
def _place_axes(axis: FloatArray, order: int, out: FloatArray) -> None:
    """diag(axis, axis) of an ``order``-state axis into the padded matrix (x at 0, y at 3)."""
    for i in range(order):
        for j in range(order):
            out[_X_AXIS + i, _X_AXIS + j] = axis[i, j]
            out[_Y_AXIS + i, _Y_AXIS + j] = axis[i, j]


@_jit
def bank_step_matrices(
    kinds: IntArray, params: FloatArray, dt: float, out_transitions: FloatArray, out_noises: FloatArray
) -> None:
    """Padded F and Q into ``out_transitions`` and ``out_noises`` (M, 8, 8) of the M models described by
    ``kinds`` (M,) and ``params`` (M, PARAMETER_COUNT) over the interval ``dt`` (see the module
    docstring). The caller allocates them: numba unpickles the dtype of every array it returns."""
    count = kinds.shape[0]
    out_transitions[:] = 0.0
    out_noises[:] = 0.0
    axis_f = np.zeros((3, 3))
    axis_q = np.zeros((3, 3))
    for b in range(count):
        kind = kinds[b]
        row = params[b]
        f = out_transitions[b]
        q = out_noises[b]
        if kind == CV or kind == CA:
            order = 2 if kind == CV else 3
            _integrator_chain(order, row[0], dt, axis_f, axis_q)
            if row[1] == DISCRETE:
                _discrete_noise(order, row[0], dt, axis_q)
            # CV's [p, v] per axis are padded components 0, 1 and 3, 4: the same places as CA's first two.
            _place_axes(axis_f, order, f)
            _place_axes(axis_q, order, q)
        elif kind == CT:
            _turn_matrix(row[2], dt, f)
            _turn_noise(row[0], row[1] == CONTINUOUS, dt, q, axis_q)
        elif kind == SINGER:
            _markov_chain(3, row[0], row[1], dt, axis_f, axis_q)
            _place_axes(axis_f, 3, f)
            _place_axes(axis_q, 3, q)
        elif kind == AT:
            _turn_noise(row[0], row[1] == CONTINUOUS, dt, q, axis_q)
            _markov_chain(2, row[2], row[3], dt, axis_f, axis_q)
            for i in range(2):
                for j in range(2):
                    f[6 + i, 6 + j] = axis_f[i, j]
                    q[6 + i, 6 + j] = axis_q[i, j]
