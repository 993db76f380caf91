"""Backward smoothing of a Gaussian chain (RTS) and of an IMM bank (Kim 1994): fixed interval and
fixed lag.

**RTS.** Rauch, Tung & Striebel (1965) in the form that needs only forward moments: with
C_k = Cov(x_k, x_{k+1} | y_1..k) and the prediction (m_{k+1|k}, P_{k+1|k}), the gain is
G_k = C_k P_{k+1|k}^-1 and

    m_{k|N} = m_k + G_k (m_{k+1|N} - m_{k+1|k}),    P_{k|N} = P_k + G_k (P_{k+1|N} - P_{k+1|k}) G_k^T.

For a linear model C_k = P_k F^T (the classic smoother); for sigma-point or cubature predictions C_k
is the points' cross covariance (Särkkä 2008, "Unscented Rauch-Tung-Striebel smoother", IEEE TAC 53).
G_k comes from the Cholesky factor L of P_{k+1|k} (W = L^-1 C_k^T, G_k^T = L^-T W), never an explicit
inverse, and the covariance is formed as D_k + G_k P_{k+1|N} G_k^T with D_k = P_k - W^T W, the
covariance of x_k given x_{k+1}: a sum of two positive semidefinite terms rather than a difference.

**IMM.** Kim (1994), "Dynamic linear models with Markov-switching", J. Econometrics 60, 1-22 (also
Kim & Nelson 1999, ch. 5): for every pair (i at k, j at k+1), model i's filtered estimate at k is
predicted through model j, and smoothed by RTS against model j's smoothed estimate at k+1;
smoothed model probabilities follow Kim's backward recursion

    mu_{k,k+1|N}(i, j) = mu_{k+1|N}(j) p_ij mu_k(i) / c_{k+1}(j),    c_{k+1}(j) = sum_i p_ij mu_k(i),
    mu_{k|N}(i) = sum_j mu_{k,k+1|N}(i, j),

and each model's pair estimates are moment-matched with the weights mu_{k,k+1|N}(i, j) / mu_{k|N}(i).
Besides the moment matching, Kim's approximation is that once s_{k+1} is given, the data after k
say nothing more about s_k, and model j's smoothed estimate at k+1 holds whatever the model at k. The
filtered probabilities may come from any forward bank (IMM or 2IMM): the recursion only uses them and
the Markov transition. The pair predictions depend on the forward pass alone, so
:func:`bank_pair_predictions` computes them once per step and a fixed-lag run only repeats the cheap
backward algebra.

Banks whose models carry different components are held padded in the 8-dim frame (``core.imm``):
zeros where a model lacks a component. A predicted covariance with a zero diagonal entry has that
component inactive: it gets zero gain. Model i's state at k enters model j with the components i
carries as they are (that is what s_k = i means) and those only j carries from j's conditional
Gaussian given the bank's common components, as the forward interaction
(``InteractingMultipleModel.mix``) gives a model its extra components. Components only i carries are
smoothed through their covariance with j's input (Stein's lemma: for Gaussian x,
Cov(x_a, f(x_b)) = Cov(x_a, x_b) Cov(x_b)^-1 Cov(x_b, f(x_b))).

**Fixed lag.** ``ends[k]`` is the last step whose data the estimate at k may use: the estimate is the
backward pass from ``ends[k]`` down to k (fixed interval: every ``ends[k]`` the last step). One pass
runs per distinct end, all in lock step, vectorised over passes: O(N L) backward steps for a lag of
L steps, in about L vectorised steps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from edgepos.core import layout
from edgepos.core.errors import NumericalError
from edgepos.core.filters.base import GaussianFilter
from edgepos.core.filters.sigma_points import SigmaPointFilter
from edgepos.core.imm import InteractingMultipleModel
from edgepos.core.motion.base import MotionModel, dt_key
from edgepos.core.numerics import FloatArray, robust_cholesky, wrap_rows

#: Window ends from a lag in seconds tolerate this much rounding in the timestamps (s).
TIME_TOLERANCE = 1e-9


@dataclass(frozen=True)
class ImmSmoothed:
    """Per-step, per-model smoothed Gaussians (padded) and smoothed model probabilities."""

    means: np.ndarray  # (N, M, n)
    covs: np.ndarray  # (N, M, n, n)
    probabilities: np.ndarray  # (N, M)


# -- the backward passes ---------------------------------------------------------------------------
def rts_smooth(
    filtered_means: np.ndarray,
    filtered_covs: np.ndarray,
    predicted_means: np.ndarray,
    predicted_covs: np.ndarray,
    cross_covs: np.ndarray,
    *,
    angle_mask: np.ndarray | None = None,
    ends: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """RTS smoothed means (N, n) and covariances (N, n, n) of a Gaussian chain.

    ``filtered_*``: step k's filtered moments, k = 0..N-1. ``predicted_*`` and ``cross_covs`` (N-1
    entries): entry k is step k+1's prediction from step k and Cov(x_k, x_{k+1}) given the data to k.
    ``angle_mask``: state entries that are angles (differences wrapped). ``ends``: see the module
    docstring (None: fixed interval).
    """
    filtered_means, filtered_covs = np.asarray(filtered_means, float), np.asarray(filtered_covs, float)
    predicted_means, predicted_covs = np.asarray(predicted_means, float), np.asarray(predicted_covs, float)
    cross_covs = np.asarray(cross_covs, float)
    count, size = filtered_means.shape
    _check_chain(count, size, filtered_covs, predicted_means, predicted_covs, cross_covs)
    mask = np.zeros(size, dtype=bool) if angle_mask is None else np.asarray(angle_mask, dtype=bool)
    gains, conditional = _gains(filtered_covs[:-1], predicted_covs, cross_covs)

    def start(last: np.ndarray) -> list[np.ndarray]:
        return [filtered_means[last].copy(), filtered_covs[last].copy()]

    def step(state: list[np.ndarray], rows: np.ndarray, k: np.ndarray) -> None:
        mean, cov = state[0][rows], state[1][rows]
        innovation = wrap_rows(mean - predicted_means[k], mask)
        new_mean = filtered_means[k] + (gains[k] @ innovation[:, :, None])[:, :, 0]
        new_cov = conditional[k] + gains[k] @ cov @ gains[k].transpose(0, 2, 1)
        state[0][rows] = wrap_rows(new_mean, mask)
        state[1][rows] = 0.5 * (new_cov + new_cov.transpose(0, 2, 1))

    means, covs = _backward(count, ends, start, step)
    _require_finite("RTS smoothed estimate", means, covs)
    return means, covs


def imm_smooth(
    means: np.ndarray,
    covs: np.ndarray,
    probabilities: np.ndarray,
    transition: np.ndarray,
    predicted_means: np.ndarray,
    predicted_covs: np.ndarray,
    cross_covs: np.ndarray,
    *,
    angle_mask: np.ndarray | None = None,
    ends: np.ndarray | None = None,
) -> ImmSmoothed:
    """Kim's IMM smoother (module docstring) over N steps of an M-model bank.

    ``means`` (N, M, n), ``covs`` (N, M, n, n), ``probabilities`` (N, M): the filtered per-model
    posteriors and model probabilities. ``transition[i, j]`` = P(model j at k+1 | model i at k).
    ``predicted_*`` and ``cross_covs`` ((N-1, M, M, n) and (N-1, M, M, n, n)): entry [k, i, j] is
    model i's estimate at k predicted through model j to k+1, and the cross covariance between
    model i's state at k and that prediction (:func:`bank_pair_predictions`).
    """
    means, covs = np.asarray(means, float), np.asarray(covs, float)
    probabilities, transition = np.asarray(probabilities, float), np.asarray(transition, float)
    count, models, size = means.shape
    if count < 1:
        raise ValueError("an IMM chain needs at least one step")
    if probabilities.shape != (count, models) or transition.shape != (models, models):
        raise ValueError("probabilities must be (N, M) and the transition (M, M)")
    pair = (count - 1, models, models)
    pair_covs_shape = (*pair, size, size)
    if (
        predicted_means.shape != (*pair, size)
        or not predicted_covs.shape == cross_covs.shape == pair_covs_shape
    ):
        raise ValueError("pair predictions must be (N-1, M, M, n) and (N-1, M, M, n, n)")
    mask = np.zeros(size, dtype=bool) if angle_mask is None else np.asarray(angle_mask, dtype=bool)
    gains, conditional = _gains(covs[:-1, :, None], predicted_covs, cross_covs)
    # mixing[k, i, j] = P(model i at k | model j at k+1, data to k) = p_ij mu_k(i) / c_{k+1}(j)
    mixing = transition[None] * probabilities[:-1, :, None]
    inflow = mixing.sum(axis=1, keepdims=True)
    mixing = mixing / np.where(inflow > 0.0, inflow, 1.0)  # no flow into j: j's smoothed mass is lost

    def start(last: np.ndarray) -> list[np.ndarray]:
        return [means[last].copy(), covs[last].copy(), probabilities[last].copy()]

    def step(state: list[np.ndarray], rows: np.ndarray, k: np.ndarray) -> None:
        later_means, later_covs, later_probabilities = (array[rows] for array in state)
        joint = mixing[k] * later_probabilities[:, None, :]  # (R, i, j): mu_{k,k+1|N}(i, j)
        marginal = joint.sum(axis=2)
        # P(model j at k+1 | model i at k, all data); a model without smoothed mass keeps its prior row
        kept = np.where(marginal > 0.0, marginal, 1.0)[:, :, None]
        backward = np.where(marginal[:, :, None] > 0.0, joint / kept, transition)
        innovation = wrap_rows(later_means[:, None, :, :] - predicted_means[k], mask)
        pair_means = wrap_rows(means[k][:, :, None, :] + (gains[k] @ innovation[..., None])[..., 0], mask)
        pair_covs = conditional[k] + gains[k] @ later_covs[:, None] @ gains[k].swapaxes(-1, -2)
        new_means, new_covs = _collapse(backward, pair_means, pair_covs, mask)
        state[0][rows], state[1][rows] = new_means, new_covs
        state[2][rows] = marginal / marginal.sum(axis=1, keepdims=True)

    smoothed_means, smoothed_covs, smoothed_probabilities = _backward(count, ends, start, step)
    _require_finite("IMM smoothed estimate", smoothed_means, smoothed_covs, smoothed_probabilities)
    return ImmSmoothed(smoothed_means, smoothed_covs, smoothed_probabilities)


def lag_ends(times: np.ndarray, lag: float) -> np.ndarray:
    """For each step, the last step at most ``lag`` seconds later (times ascending): the ``ends`` of
    a fixed-lag smoother that may use the data up to t + lag."""
    times = np.asarray(times, dtype=float)
    return np.searchsorted(times, times + lag + TIME_TOLERANCE, side="right") - 1


def _check_chain(
    count: int,
    size: int,
    filtered_covs: np.ndarray,
    predicted_means: np.ndarray,
    predicted_covs: np.ndarray,
    cross_covs: np.ndarray,
) -> None:
    if count < 1 or filtered_covs.shape != (count, size, size):
        raise ValueError("filtered moments must be (N, n) and (N, n, n) with N >= 1")
    if np.shape(predicted_means) != (count - 1, size):
        raise ValueError("predicted means must be (N-1, n)")
    if np.shape(predicted_covs) != (count - 1, size, size) or np.shape(cross_covs) != (count - 1, size, size):
        raise ValueError("predicted and cross covariances must be (N-1, n, n)")


def _gains(
    filtered_covs: np.ndarray, predicted_covs: np.ndarray, cross_covs: np.ndarray
) -> tuple[FloatArray, FloatArray]:
    """Smoother gains G = C P^-1 and conditional covariances D = P_k - C P^-1 C^T through the
    Cholesky factor of each predicted covariance (inactive, zero-variance components: identity)."""
    size = predicted_covs.shape[-1]
    inactive = np.diagonal(predicted_covs, axis1=-2, axis2=-1) == 0.0
    padded = predicted_covs + inactive[..., None, :] * np.eye(size)
    try:
        factor = np.linalg.cholesky(padded)
    except np.linalg.LinAlgError:
        raise NumericalError("a predicted covariance is not positive definite") from None
    whitened = np.linalg.solve(factor, cross_covs.swapaxes(-1, -2))  # W = L^-1 C^T
    gains = np.linalg.solve(factor.swapaxes(-1, -2), whitened).swapaxes(-1, -2)
    conditional = filtered_covs - whitened.swapaxes(-1, -2) @ whitened
    conditional = 0.5 * (conditional + conditional.swapaxes(-1, -2))
    _require_finite("smoother gain", gains, conditional)
    return gains, conditional


def _collapse(
    weights: np.ndarray, means: np.ndarray, covs: np.ndarray, mask: np.ndarray
) -> tuple[FloatArray, FloatArray]:
    """Moment match over the last model axis: weights (..., J), means (..., J, n), covs (..., J, n, n)."""
    column = weights[..., None]
    mean = (column * means).sum(axis=-2)
    if mask.any():
        angles = means[..., mask]
        mean[..., mask] = np.arctan2(
            (column * np.sin(angles)).sum(axis=-2), (column * np.cos(angles)).sum(axis=-2)
        )
    spread = wrap_rows(means - mean[..., None, :], mask)
    cov = (column[..., None] * covs).sum(axis=-3) + (spread * column).swapaxes(-1, -2) @ spread
    return mean, 0.5 * (cov + cov.swapaxes(-1, -2))


def _backward(
    count: int,
    ends: np.ndarray | None,
    start: Callable[[np.ndarray], list[np.ndarray]],
    step: Callable[[list[np.ndarray], np.ndarray, np.ndarray], None],
) -> list[np.ndarray]:
    """One backward pass per distinct window end, in lock step; returns each step's estimate.

    ``start(last)`` gives the passes' initial state (arrays with one row per pass) at steps ``last``;
    ``step(state, rows, k)`` moves passes ``rows`` from step k+1 back to k, in place. A pass is read
    at each step k whose window ends where the pass began.
    """
    ends = np.full(count, count - 1) if ends is None else np.asarray(ends)
    steps = np.arange(count)
    if ends.shape != (count,) or not np.issubdtype(ends.dtype, np.integer):
        raise ValueError("ends must hold one integer step index per step")
    if np.any(ends < steps) or np.any(ends > count - 1) or np.any(np.diff(ends) < 0):
        raise ValueError("ends must be non-decreasing with k <= ends[k] <= N-1")
    last, first = np.unique(ends, return_index=True)  # passes: their end and the first step they serve
    state = start(last)
    out = [np.empty((count, *array.shape[1:])) for array in state]
    position = last.copy()

    def read(rows: np.ndarray) -> None:
        served = rows[ends[position[rows]] == last[rows]]
        for result, array in zip(out, state):
            result[position[served]] = array[served]

    read(np.arange(last.size))
    while True:
        rows = np.flatnonzero(position > first)
        if rows.size == 0:
            return out
        position[rows] -= 1
        step(state, rows, position[rows])
        read(rows)


def _require_finite(name: str, *arrays: np.ndarray) -> None:
    for array in arrays:
        if not np.isfinite(array).all():
            raise NumericalError(f"{name} is not finite")


# -- the pair predictions of a bank ------------------------------------------------------------------
def predict_with_cross(
    filt: GaussianFilter, model: MotionModel, means: np.ndarray, covs: np.ndarray, dts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each padded Gaussian (R, 8) / (R, 8, 8) predicted over its ``dts`` (R,) by ``model`` as ``filt``
    predicts it, with the cross covariance Cov(x, x') of the state before and after: padded
    (R, 8), (R, 8, 8), (R, 8, 8).

    Linear models: F m, F P F^T + Q and P F^T (every filter's prediction is then exact). Nonlinear
    ones: the sigma-point filters' points (their cross covariance), the EKF's Jacobian at the mean
    (P J^T). Intervals are taken to the 1 ns of the discretisation caches; dt 0 is the identity.
    """
    idx = np.array(model.components)
    dim = idx.size
    sub_means, sub_covs = means[:, idx], covs[:, idx[:, None], idx[None, :]]
    keys = np.array([dt_key(dt) for dt in np.atleast_1d(dts)])
    if keys.size == 1 and means.shape[0] > 1:
        keys = np.full(means.shape[0], keys[0])
    new_means, new_covs, crosses = np.empty_like(sub_means), np.empty_like(sub_covs), np.empty_like(sub_covs)
    mask = layout.angle_mask(model.components)
    for dt in np.unique(keys):
        rows = np.flatnonzero(keys == dt)
        mean, cov = sub_means[rows], sub_covs[rows]
        if dt == 0.0:
            new_means[rows], new_covs[rows], crosses[rows] = mean, cov, cov
            continue
        if model.linear:
            transition = model.transition_matrix(np.zeros(dim), dt)
            cross = cov @ transition.T
            predicted, spread = mean @ transition.T, transition @ cross
        elif isinstance(filt, SigmaPointFilter):
            predicted, spread, cross = _sigma_point_prediction(filt, model, mean, cov, dt, mask)
        else:  # first order: the Jacobian at each mean
            jacobians = np.stack([model.transition_matrix(m, dt) for m in mean])
            cross = cov @ jacobians.transpose(0, 2, 1)
            predicted, spread = model.propagate(mean, dt), jacobians @ cross
        if model.state_dependent_noise:
            noise = np.stack([model.noise_covariance(m, dt) for m in mean])
        else:
            noise = model.noise_covariance(np.zeros(dim), dt)
        new_means[rows], new_covs[rows], crosses[rows] = wrap_rows(predicted, mask), spread + noise, cross
    new_covs = 0.5 * (new_covs + new_covs.transpose(0, 2, 1))
    out_means = np.zeros(means.shape)
    out_covs, out_crosses = np.zeros(covs.shape), np.zeros(covs.shape)
    out_means[:, idx] = new_means
    out_covs[:, idx[:, None], idx[None, :]] = new_covs
    out_crosses[:, idx[:, None], idx[None, :]] = crosses
    return out_means, out_covs, out_crosses


def _sigma_point_prediction(
    filt: SigmaPointFilter, model: MotionModel, mean: FloatArray, cov: FloatArray, dt: float, mask: np.ndarray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Points mean + s L e_i through f: predicted mean, the points' covariance (without Q) and the
    cross covariance sum_i w_i (X_i - m)(f(X_i) - m')^T."""
    offsets, mean_weights, cov_weights = filt.unit_points(mean.shape[1])
    try:
        factors = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        factors = np.stack([robust_cholesky(c) for c in cov])
    before = offsets[None] @ factors.transpose(0, 2, 1)  # (R, points, m)
    count, points, dim = before.shape
    moved = model.propagate((mean[:, None, :] + before).reshape(count * points, dim), dt)
    moved = moved.reshape(count, points, dim)
    predicted = np.einsum("p,rpm->rm", mean_weights, moved)
    if mask.any():
        angles = moved[:, :, mask]
        sines, cosines = (np.einsum("p,rpm->rm", mean_weights, f(angles)) for f in (np.sin, np.cos))
        predicted[:, mask] = np.arctan2(sines, cosines)
    after = wrap_rows(moved - predicted[:, None, :], mask)
    weighted = after * cov_weights[None, :, None]
    return predicted, weighted.transpose(0, 2, 1) @ after, before.transpose(0, 2, 1) @ weighted


def bank_pair_predictions(
    bank: InteractingMultipleModel, means: np.ndarray, covs: np.ndarray, dts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kim's pair predictions of a bank's filtered posteriors: means (N, M, 8) and covs (N, M, 8, 8)
    at N steps, ``dts`` (N-1,) the intervals between them. Returns the predicted means
    (N-1, M, M, 8), covariances and cross covariances (N-1, M, M, 8, 8): entry [k, i, j] is model i's
    estimate at k predicted through model j, and Cov(model i's state at k, that prediction).
    """
    count = len(bank.models)
    steps = means.shape[0] - 1
    predicted_means = np.zeros((steps, count, count, layout.FULL_DIM))
    predicted_covs = np.zeros((steps, count, count, layout.FULL_DIM, layout.FULL_DIM))
    cross_covs = np.zeros_like(predicted_covs)
    if steps == 0:
        return predicted_means, predicted_covs, cross_covs
    for i in range(count):
        for j, model in enumerate(bank.models):
            mean, cov = _hand_over(bank, means[:-1], covs[:-1], i, j)
            active = bank.active[j]
            inputs = np.flatnonzero(active)
            prediction, predicted_cov, cross = predict_with_cross(
                bank.filter, model, mean * active, cov * np.outer(active, active), dts
            )
            predicted_means[:, i, j], predicted_covs[:, i, j] = prediction, predicted_cov
            shared = np.flatnonzero(bank.active[i] & active)
            cross_covs[:, i, j, shared] = cross[:, shared]
            own = np.flatnonzero(bank.active[i] & ~active)
            if own.size:  # Stein: Cov(x_own, x') = Cov(x_own, x_in) Cov(x_in)^-1 Cov(x_in, x')
                try:
                    regression = np.linalg.solve(
                        cov[:, inputs[:, None], inputs[None, :]], cov[:, inputs[:, None], own[None, :]]
                    ).transpose(0, 2, 1)
                except np.linalg.LinAlgError:
                    raise NumericalError("a model's input covariance is singular") from None
                cross_covs[:, i, j, own] = regression @ cross[:, inputs]
    return predicted_means, predicted_covs, cross_covs


def _hand_over(
    bank: InteractingMultipleModel, means: np.ndarray, covs: np.ndarray, i: int, j: int
) -> tuple[FloatArray, FloatArray]:
    """Model i's posteriors (steps, 8) / (steps, 8, 8), extended by the components only model j
    carries: their conditional Gaussian in model j given the common components, shifted to model i's
    common block, as the bank's interaction gives a model its extra components
    (``InteractingMultipleModel.mix``)."""
    mean, cov = means[:, i].copy(), covs[:, i].copy()
    extra = np.flatnonzero(bank.active[j] & ~bank.active[i])
    if extra.size == 0:
        return mean, cov
    common = np.array(bank.common)
    own_cc = covs[:, j][:, common[:, None], common[None, :]]
    own_ec = covs[:, j][:, extra[:, None], common[None, :]]
    try:
        regression = np.linalg.solve(own_cc, own_ec.transpose(0, 2, 1)).transpose(0, 2, 1)  # B = P_ec P_cc^-1
    except np.linalg.LinAlgError:
        raise NumericalError("common-component covariance is singular") from None
    shift = wrap_rows(means[:, i, common] - means[:, j, common], bank.common_mask)
    mean[:, extra] = means[:, j, extra] + (regression @ shift[:, :, None])[:, :, 0]
    cross = regression @ cov[:, common, :]  # Cov(x_extra, x) = B Cov(x_common, x)
    cov[:, extra, :] = cross
    cov[:, :, extra] = cross.transpose(0, 2, 1)
    own_ee = covs[:, j][:, extra[:, None], extra[None, :]]
    cov[:, extra[:, None], extra[None, :]] = (
        own_ee - regression @ own_ec.transpose(0, 2, 1) + cross[:, :, common] @ regression.transpose(0, 2, 1)
    )
    return wrap_rows(mean, layout.FULL_ANGLE_MASK), 0.5 * (cov + cov.transpose(0, 2, 1))
