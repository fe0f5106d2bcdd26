"""Covariance repair for the localizer's UKF: symmetrising, a square root that never fails.

The filter symmetrises ``P`` after every step (:func:`symmetrise`), clips it back to
positive definite when a Cholesky factorisation fails (:func:`make_pd`) and takes its
sigma-point square root with :func:`robust_sqrt` (Cholesky, then escalating diagonal
jitter, then an eigenvalue clip), so a nearly singular ``P`` never makes it raise.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cholesky

__all__ = ["symmetrise", "robust_sqrt", "make_pd"]


def symmetrise(p: np.ndarray) -> np.ndarray:
    """``(P + P.T) / 2``: the symmetric part of a square matrix."""
    return 0.5 * (p + p.T)


def robust_sqrt(p: np.ndarray) -> np.ndarray:
    """Upper-triangular square root ``U`` (``U.T @ U = P``) that never raises on a bad P.

    Tries :func:`scipy.linalg.cholesky` on the symmetrised matrix, then with diagonal
    jitter growing from ``1e-12`` to ``1e-3`` times the mean diagonal, then falls back
    to an eigen-decomposition with negative eigenvalues clipped (returned as the upper
    factor of a QR of ``diag(sqrt(w)) V.T``).

    Parameters
    ----------
    p : ndarray (n, n)
        A covariance-like matrix (already scaled as the sigma points need it).

    Raises
    ------
    ValueError
        If ``p`` is not square or contains non-finite values.
    """
    p = np.asarray(p, float)
    if p.ndim != 2 or p.shape[0] != p.shape[1]:
        raise ValueError(f"matrix must be square, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("matrix has non-finite values")
    p = symmetrise(p)
    try:
        return cholesky(p, lower=False, check_finite=False)
    except np.linalg.LinAlgError:
        pass
    scale = max(float(np.mean(np.abs(np.diag(p)))), 1e-300)
    eye = np.eye(p.shape[0])
    for k in range(-12, -2):
        try:
            return cholesky(p + (10.0 ** k) * scale * eye, lower=False, check_finite=False)
        except np.linalg.LinAlgError:
            continue
    w, v = np.linalg.eigh(p)
    half = np.sqrt(np.clip(w, 1e-12 * scale, None))[:, None] * v.T
    r = np.linalg.qr(half, mode="r")
    return r


def make_pd(p: np.ndarray) -> np.ndarray:
    """Symmetrise; if a Cholesky factorisation fails, clip the eigenvalues to be > 0."""
    p = symmetrise(p)
    try:
        np.linalg.cholesky(p)
        return p
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(p)
        floor = 1e-12 * max(float(np.max(np.abs(w))), 1e-300)
        return symmetrise((v * np.clip(w, floor, None)) @ v.T)
