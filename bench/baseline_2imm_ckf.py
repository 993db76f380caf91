"""A direct numpy transcription of one 2IMM-CKF step (RSU + IMU paper, eqs. 11-38), model by model.

This is the yardstick for ``bench/filter_step.py``: the same mathematics as the project's bank
(standard cubature forms, mixing of the common components with the extra ones carried by their
conditional), written the obvious way: a loop over models, cubature points for every prediction,
explicit inverses. It shares only the motion and measurement models with the project, so the
benchmark can also check that both give the same answer.
"""

from __future__ import annotations

import numpy as np


def _cubature(mean, cov):
    dim = mean.size
    root = np.linalg.cholesky(cov)
    unit = np.sqrt(dim) * np.hstack([np.eye(dim), -np.eye(dim)])
    return mean[:, None] + root @ unit, np.full(2 * dim, 1.0 / (2 * dim))


def _wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def step(models, transition, priority, means, covs, probabilities, dt, measurement, observed):
    """One epoch; ``means``/``covs`` are per-model sub-state lists. Returns the new lists, the
    probabilities and the fused (mean, cov) over the common components."""
    count = len(models)
    common = sorted(set.intersection(*(set(m.components) for m in models)))
    local = [[list(m.components).index(c) for c in common] for m in models]
    # Interaction (eqs. 11-14) over the common components.
    predicted = transition.T @ probabilities
    mixing = np.zeros((count, count))
    for i in range(count):
        for j in range(count):
            mixing[i, j] = transition[i, j] * probabilities[i] / predicted[j]
    mixed_means, mixed_covs = [], []
    for j in range(count):
        mean_c = sum(mixing[i, j] * means[i][local[i]] for i in range(count))
        cov_c = sum(
            mixing[i, j]
            * (
                covs[i][np.ix_(local[i], local[i])]
                + np.outer(means[i][local[i]] - mean_c, means[i][local[i]] - mean_c)
            )
            for i in range(count)
        )
        mean, cov = means[j].copy(), covs[j].copy()
        extra = [k for k in range(len(mean)) if k not in local[j]]
        if extra:
            c = local[j]
            regression = cov[np.ix_(extra, c)] @ np.linalg.inv(cov[np.ix_(c, c)])
            mean[extra] = means[j][extra] + regression @ (mean_c - means[j][c])
            conditional = cov[np.ix_(extra, extra)] - regression @ cov[np.ix_(c, extra)]
            cov[np.ix_(extra, c)] = regression @ cov_c
            cov[np.ix_(c, extra)] = (regression @ cov_c).T
            cov[np.ix_(extra, extra)] = conditional + regression @ cov_c @ regression.T
        mean[local[j]] = mean_c
        cov[np.ix_(local[j], local[j])] = cov_c
        mixed_means.append(mean)
        mixed_covs.append(cov)
    # Each model's cubature filter (eqs. 15-28).
    new_means, new_covs, likelihoods = [], [], []
    for j, model in enumerate(models):
        points, weights = _cubature(mixed_means[j], mixed_covs[j])
        moved = model.propagate(points.T, dt).T
        prior = moved @ weights
        if 6 in model.components:
            phi = list(model.components).index(6)
            prior[phi] = np.arctan2(np.sin(moved[phi]) @ weights, np.cos(moved[phi]) @ weights)
        deviation = moved - prior[:, None]
        prior_cov = deviation * weights @ deviation.T + model.noise_covariance(mixed_means[j], dt)
        points, weights = _cubature(prior, prior_cov)
        full = np.zeros((points.shape[1], 8))
        full[:, list(model.components)] = points.T
        z_points = measurement.predict(full).T
        z_mean = z_points @ weights
        angles = measurement.angle_mask
        z_mean[angles] = np.arctan2(np.sin(z_points[angles]) @ weights, np.cos(z_points[angles]) @ weights)
        z_dev = z_points - z_mean[:, None]
        z_dev[angles] = _wrap(z_dev[angles])
        innovation_cov = z_dev * weights @ z_dev.T + measurement.noise_covariance()
        cross_cov = (points - prior[:, None]) * weights @ z_dev.T
        inverse = np.linalg.inv(innovation_cov)
        gain = cross_cov @ inverse
        residual = observed - z_mean
        residual[angles] = _wrap(residual[angles])
        new_means.append(prior + gain @ residual)
        new_covs.append(prior_cov - gain @ innovation_cov @ gain.T)
        likelihoods.append(
            np.exp(-0.5 * residual @ inverse @ residual) / np.sqrt(np.linalg.det(2 * np.pi * innovation_cov))
        )
    likelihoods = np.array(likelihoods)
    first = list(priority)
    second = [i for i in range(count) if i not in first]
    # First interaction (eqs. 30-32).
    mu = likelihoods[first] * predicted[first] / np.sum(likelihoods[first] * predicted[first])
    x0 = sum(mu[k] * new_means[i][local[i]] for k, i in enumerate(first))
    p0 = sum(
        mu[k]
        * (
            new_covs[i][np.ix_(local[i], local[i])]
            + np.outer(new_means[i][local[i]] - x0, new_means[i][local[i]] - x0)
        )
        for k, i in enumerate(first)
    )
    # Second interaction (eqs. 33-37) and the probability update (eq. 38).
    best = likelihoods[first].max()
    denominator = best * predicted[first].sum() + np.sum(likelihoods[second] * predicted[second])
    mu0 = best * predicted[first].sum() / denominator
    mu_second = likelihoods[second] * predicted[second] / denominator
    fused = mu0 * x0 + sum(mu_second[k] * new_means[i][local[i]] for k, i in enumerate(second))
    fused_cov = mu0 * (p0 + np.outer(x0 - fused, x0 - fused)) + sum(
        mu_second[k]
        * (
            new_covs[i][np.ix_(local[i], local[i])]
            + np.outer(new_means[i][local[i]] - fused, new_means[i][local[i]] - fused)
        )
        for k, i in enumerate(second)
    )
    probabilities = np.zeros(count)
    probabilities[first] = mu * mu0
    probabilities[second] = mu_second
    return new_means, new_covs, probabilities, fused, fused_cov
