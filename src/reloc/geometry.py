"""The one home of the geometry conventions: angle wrapping, cross-product matrices, SO(3).

- Angles are radians, wrapped to ``[-pi, pi)`` by :func:`wrap_angle`; an angle already in that
  interval is returned unchanged (no rounding through ``a + pi - pi``), one outside it as
  ``(a + pi) mod 2 pi - pi``. Every package (``reloc``, ``ekf``, ``fgslam``) uses this function.
- ``skew(a) @ b = a x b``.
- Rotations are (3, 3) matrices; a rotation vector ``w`` (3,) rad maps to ``Exp(w)`` by
  :func:`exp_so3` (Rodrigues) and back by :func:`log_so3` (angle < pi).
- Heading: :func:`yaw_of` is the angle of base_link's x axis in the world xy plane,
  ``atan2(R[1, 0], R[0, 0])``, for a rotation (3, 3) or a pose (4, 4), or stacks of either.

The scalar paths use :mod:`math` (these run on every filter step); array inputs go through numpy.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["exp_so3", "log_so3", "project_so3", "skew", "wrap_angle", "yaw_of"]

_I3 = np.eye(3)
_PI = math.pi
_TWO_PI = 2.0 * math.pi


def wrap_angle(a):
    """Angle(s) ``a`` (rad, float or array) wrapped to ``[-pi, pi)``; a float gives a float."""
    if isinstance(a, float | int):
        a = float(a)
        if -_PI <= a < _PI:
            return a
        return (a + _PI) % _TWO_PI - _PI
    a = np.asarray(a, dtype=float)
    inside = (a >= -_PI) & (a < _PI)
    if np.all(inside):
        return a.copy() if a.ndim else a
    return np.where(inside, a, (a + _PI) % _TWO_PI - _PI)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices: (3,) -> (3, 3), or (..., 3) -> (..., 3, 3), ``skew(a) @ b = a x b``."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:
        x, y, z = float(v[0]), float(v[1]), float(v[2])
        return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


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


def project_so3(R: np.ndarray) -> np.ndarray:
    """The nearest rotation to ``R`` (3, 3) (SVD), to remove round-off drift."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def yaw_of(M: np.ndarray):
    """Heading (rad) of base_link x in the world xy plane: ``atan2(M[1, 0], M[0, 0])`` of a
    rotation (3, 3) or pose (4, 4) (a float), or of stacks (..., 3, 3) / (..., 4, 4) (an array)."""
    M = np.asarray(M)
    if M.ndim == 2:
        return math.atan2(M[1, 0], M[0, 0])
    return np.arctan2(M[..., 1, 0], M[..., 0, 0])
