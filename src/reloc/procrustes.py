"""2D similarity transforms by Procrustes (Umeyama 1991), proper rotations only.

``dst ~= scale * R(theta) @ src + t``. :func:`umeyama_2d` fits one transform to K >= 2 point pairs
(optionally weighted): the SVD of the cross-covariance with the reflection correction, which in
2D has a closed form, so det R = +1 always: a mirrored constellation gets a poor fit instead of
a mirrored transform.
:func:`similarity_batch` is the closed form of the same fit for H small correspondence sets at once
(in 2D the optimal rotation angle is ``atan2(sum p x q, sum p . q)`` on centred points).
"""

from __future__ import annotations

import math
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
        xy = np.asarray(xy, float)
        c, s = self.scale * math.cos(self.theta_rad), self.scale * math.sin(self.theta_rad)
        out = np.empty(xy.shape)
        out[..., 0] = c * xy[..., 0] - s * xy[..., 1] + self.translation[0]
        out[..., 1] = s * xy[..., 0] + c * xy[..., 1] + self.translation[1]
        return out


def umeyama_2d(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, *, with_scale: bool = True
) -> Similarity2D:
    """Least-squares similarity mapping ``src`` (K, 2) onto ``dst`` (K, 2), K >= 2, det R = +1."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2 or src.shape[0] < 2:
        raise ValueError(f"umeyama_2d needs two (K>=2, 2) arrays of equal shape, got {src.shape}, {dst.shape}")
    n = src.shape[0]
    w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, float) / np.sum(weights)
    mu_s = w @ src
    mu_d = w @ dst
    p = src - mu_s
    q = dst - mu_d
    # in 2D the SVD solution with the reflection fix is the closed form: the proper rotation
    # maximising sum w (q . R p) has angle atan2(sum w p x q, sum w p . q)
    dot = float(w @ (p[:, 0] * q[:, 0] + p[:, 1] * q[:, 1]))
    crs = float(w @ (p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]))
    theta = math.atan2(crs, dot)
    var_s = float(w @ (p[:, 0] * p[:, 0] + p[:, 1] * p[:, 1]))
    scale = math.hypot(dot, crs) / var_s if (with_scale and var_s > 0) else 1.0
    c, s = math.cos(theta), math.sin(theta)
    t = mu_d - scale * np.array([c * mu_s[0] - s * mu_s[1], s * mu_s[0] + c * mu_s[1]])
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
