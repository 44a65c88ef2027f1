"""2D similarity transforms by Procrustes (Umeyama 1991), proper rotations only.

``dst ~= scale * R(theta) @ src + t``. :func:`umeyama_2d` fits one transform to K >= 2 point pairs
(optionally weighted) via the SVD of the cross-covariance with the reflection correction, so
det R = +1 always: a mirrored constellation gets a poor fit instead of a mirrored transform.
:func:`similarity_batch` is the closed form of the same fit for H small correspondence sets at once
(in 2D the optimal rotation angle is ``atan2(sum p x q, sum p . q)`` on centred points).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Similarity2D", "rotation_2d", "similarity_batch", "umeyama_2d"]


def rotation_2d(theta_rad: float | np.ndarray) -> np.ndarray:
    """Rotation matrix (2, 2) (or (..., 2, 2) for an array of angles)."""
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


@dataclass(frozen=True, slots=True)
class Similarity2D:
    """``dst = scale * R(theta_rad) @ src + translation``; ``translation`` (2,) in dst units."""

    theta_rad: float
    translation: np.ndarray
    scale: float

    @property
    def rotation(self) -> np.ndarray:
        """(2, 2) rotation matrix, det +1."""
        return rotation_2d(self.theta_rad)

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """Map points (N, 2) from the source to the destination frame."""
        return self.scale * np.asarray(xy, float) @ self.rotation.T + self.translation


def umeyama_2d(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, *, with_scale: bool = True
) -> Similarity2D:
    """Least-squares similarity mapping ``src`` (K, 2) onto ``dst`` (K, 2), K >= 2, det R = +1."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2 or src.shape[0] < 2:
        raise ValueError(f"umeyama_2d needs two (K>=2, 2) arrays of equal shape, got {src.shape}, {dst.shape}")
    w = np.ones(src.shape[0]) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    s0 = src - mu_s
    d0 = dst - mu_d
    cov = (d0 * w[:, None]).T @ s0  # (2, 2) cross-covariance dst x src
    u, sv, vt = np.linalg.svd(cov)
    fix = np.diag([1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    rot = u @ fix @ vt
    var_s = float(np.sum(w * np.sum(s0 * s0, axis=1)))
    scale = float(np.trace(np.diag(sv) @ fix) / var_s) if (with_scale and var_s > 0) else 1.0
    theta = float(np.arctan2(rot[1, 0], rot[0, 0]))
    t = mu_d - scale * rot @ mu_s
    return Similarity2D(theta, t, scale)


def similarity_batch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form 2D similarity for H sets of K pairs: ``src``/``dst`` (H, K, 2).

    Returns ``theta_rad`` (H,), ``scale`` (H,), ``translation`` (H, 2). Proper rotations only.
    """
    mu_s = src.mean(axis=1, keepdims=True)
    mu_d = dst.mean(axis=1, keepdims=True)
    p = src - mu_s
    q = dst - mu_d
    dot = np.sum(p[..., 0] * q[..., 0] + p[..., 1] * q[..., 1], axis=1)
    crs = np.sum(p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0], axis=1)
    theta = np.arctan2(crs, dot)
    var_p = np.sum(p * p, axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.hypot(dot, crs) / var_p
    c, s = np.cos(theta), np.sin(theta)
    ms = mu_s[:, 0]
    md = mu_d[:, 0]
    t = md - scale[:, None] * np.stack([c * ms[:, 0] - s * ms[:, 1], s * ms[:, 0] + c * ms[:, 1]], 1)
    return theta, scale, t
