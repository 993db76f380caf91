"""Small numerical helpers shared by the filters: angle wrapping, symmetry, robust Cholesky."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from edgepos.core.errors import NumericalError

TWO_PI = 2.0 * math.pi

#: float64 arrays: states, covariances, weights.
FloatArray = npt.NDArray[np.float64]


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle) + math.pi) % TWO_PI - math.pi


def wrap_rows(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Wrap the entries of ``values`` (last axis) selected by ``mask`` in place; return it."""
    if mask.any():
        values[..., mask] = (values[..., mask] + math.pi) % TWO_PI - math.pi
    return values


def weighted_mean(points: np.ndarray, weights: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Weighted mean of rows; entries flagged in ``mask`` are angles and get a circular mean."""
    mean: FloatArray = weights @ points
    if mask.any():
        angles = points[:, mask]
        mean[mask] = np.arctan2(weights @ np.sin(angles), weights @ np.cos(angles))
    return mean


def symmetrize(matrix: FloatArray) -> FloatArray:
    """Return (M + M^T) / 2, removing the asymmetry that rounding accumulates."""
    return 0.5 * (matrix + matrix.T)


def robust_cholesky(cov: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a covariance, repairing a nearly singular one.

    First the plain factorisation; if that fails, a jitter of growing size (relative to the
    diagonal) is added; as a last resort negative eigenvalues are clipped. A matrix that is not
    finite, or indefinite well beyond rounding, raises :class:`NumericalError`.
    """
    if not np.all(np.isfinite(cov)):
        raise NumericalError("covariance has non-finite entries")
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        pass
    sym = symmetrize(cov)
    scale = max(float(np.max(np.abs(np.diag(sym)))), 1e-300)
    identity = np.eye(sym.shape[0])
    for relative in (1e-12, 1e-10, 1e-8):
        try:
            return np.linalg.cholesky(sym + relative * scale * identity)
        except np.linalg.LinAlgError:
            continue
    eigenvalues, eigenvectors = np.linalg.eigh(sym)
    if eigenvalues.min() < -1e-6 * scale:
        raise NumericalError(
            f"covariance is indefinite (smallest eigenvalue {eigenvalues.min():.3g}, "
            f"largest {eigenvalues.max():.3g})"
        )
    clipped = np.maximum(eigenvalues, 1e-9 * scale)
    return np.linalg.cholesky(symmetrize((eigenvectors * clipped) @ eigenvectors.T))


def require_finite(name: str, *arrays: np.ndarray) -> None:
    """Raise :class:`NumericalError` if any array holds NaN or infinity.

    A sum is non-finite exactly when some entry is (or entries overflow it, which is as bad), and
    one reduction per array is cheaper than an elementwise test.
    """
    for array in arrays:
        if not math.isfinite(float(array.sum())):
            raise NumericalError(f"{name} is not finite")
