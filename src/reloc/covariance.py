"""The one home of covariance hygiene: the positive semi-definite part of a symmetric matrix, and
the variance factor of fixes correlated along the path."""

from __future__ import annotations

import numpy as np

__all__ = ["distance_correlation_scale", "psd_part"]


def psd_part(C: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """The symmetric part of ``C`` (..., n, n) with its eigenvalues clipped to at least ``floor``
    (0: the nearest positive semi-definite matrix in the Frobenius norm)."""
    C = np.asarray(C, dtype=float)
    w, V = np.linalg.eigh(0.5 * (C + np.swapaxes(C, -1, -2)))
    return np.einsum("...ij,...j,...kj->...ik", V, np.maximum(w, floor), V)


def distance_correlation_scale(distance_m: float, length_m: float) -> float:
    """Covariance multiplier of a fix made ``distance_m`` of path after the previous one, when the
    fixes' errors are a first-order Gauss-Markov process along the path (correlation
    ``rho = exp(-d / length_m)``: the catalog errors of the landmarks two fixes share) and a
    back-end fuses them as independent: ``(1 + rho) / (1 - rho)``, the variance of the mean of
    such a sequence over that of as many independent fixes. A fix at the same place (``d`` -> 0)
    adds almost nothing; ``d`` is floored at 1 % of the length (a multiplier of ~200)."""
    rho = float(np.exp(-max(float(distance_m), 0.01 * length_m) / length_m))
    return (1.0 + rho) / (1.0 - rho)
