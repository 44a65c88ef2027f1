"""The one home of covariance hygiene: the positive semi-definite part of a symmetric matrix."""

from __future__ import annotations

import numpy as np

__all__ = ["psd_part"]


def psd_part(C: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """The symmetric part of ``C`` (..., n, n) with its eigenvalues clipped to at least ``floor``
    (0: the nearest positive semi-definite matrix in the Frobenius norm)."""
    C = np.asarray(C, dtype=float)
    w, V = np.linalg.eigh(0.5 * (C + np.swapaxes(C, -1, -2)))
    return np.einsum("...ij,...j,...kj->...ik", V, np.maximum(w, floor), V)
