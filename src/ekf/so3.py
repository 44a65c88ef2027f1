"""Small, fast SO(3) helpers for single rotations (Rodrigues), used on every filter step."""

from __future__ import annotations

import math

import numpy as np

from reloc.landmark_model import skew

_I3 = np.eye(3)

__all__ = ["exp_so3", "log_so3", "project_so3", "skew", "yaw_of"]


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``w`` (3,) rad."""
    x, y, z = float(w[0]), float(w[1]), float(w[2])
    th = math.sqrt(x * x + y * y + z * z)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    K2 = K @ K
    if th < 1e-8:
        return _I3 + K + 0.5 * K2
    return _I3 + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / (th * th)) * K2


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) rad of the rotation matrix ``R`` (3, 3) (angle < pi)."""
    c = min(1.0, max(-1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    th = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-8:
        return 0.5 * v
    if th > math.pi - 1e-6:
        # near pi the antisymmetric part vanishes: take the axis from the symmetric part
        B = 0.5 * (R + np.eye(3))
        axis = B[int(np.argmax(np.diag(B)))]
        axis = axis / np.linalg.norm(axis)
        return th * axis
    return (th / (2.0 * math.sin(th))) * v


def yaw_of(R: np.ndarray) -> float:
    """Heading (rad) of base_link x in the world xy plane."""
    return math.atan2(R[1, 0], R[0, 0])


def project_so3(R: np.ndarray) -> np.ndarray:
    """The nearest rotation to ``R`` (3, 3) (SVD), to remove round-off drift."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def wrap_angle(a: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi
