"""Stereo point-landmark measurement model shared by both back-ends.

A rock is a 3D point ``l_world``; the stereo front-end measures it in base_link as
``z_base = R_world_base^T (l_world - p_world)`` with covariance ``R_z`` (stereo triangulation,
depth variance growing with range squared).

Jacobians use the pose error convention of :mod:`reloc.backend`: the true pose is
``R_true = Exp(dtheta_world) @ R_est``, ``p_true = p_est + dp_world``; the pose error vector is
``[dp_world (3), dtheta_world (3)]``.
"""

from __future__ import annotations

import numpy as np

from reloc.geometry import skew


def point_in_base(R_world_base: np.ndarray, p_world: np.ndarray, l_world: np.ndarray) -> np.ndarray:
    """Predicted measurements ``z = R^T (l - p)``: landmarks ``l_world`` (M, 3) m -> base_link (M, 3) m."""
    l_world = np.reshape(np.asarray(l_world, dtype=float), (-1, 3))
    return (l_world - np.asarray(p_world, dtype=float)) @ np.asarray(R_world_base, dtype=float)


def point_to_world(
    R_world_base: np.ndarray, p_world: np.ndarray, z_base: np.ndarray, R_z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Detections ``z_base`` (N, 3) m with covariance ``R_z`` (N, 3, 3) m^2 -> world points (N, 3)
    and their covariance (N, 3, 3), the pose taken as exact (``l = p + R z``, ``C = R R_z R^T``)."""
    R = np.asarray(R_world_base, dtype=float)
    z_base = np.reshape(np.asarray(z_base, dtype=float), (-1, 3))
    R_z = np.reshape(np.asarray(R_z, dtype=float), (-1, 3, 3))
    l_world = np.asarray(p_world, dtype=float) + z_base @ R.T
    cov_world = np.einsum("ij,njk,lk->nil", R, R_z, R)
    return l_world, cov_world


def point_jacobians(
    R_world_base: np.ndarray, p_world: np.ndarray, l_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of ``z = R^T (l - p)`` for landmarks (M, 3): ``H_pose`` (M, 3, 6) w.r.t. the pose
    error ``[dp_world, dtheta_world]`` and ``H_l`` (3, 3) (= R^T, the same for every landmark)."""
    R = np.asarray(R_world_base, dtype=float)
    d = np.reshape(np.asarray(l_world, dtype=float), (-1, 3)) - np.asarray(p_world, dtype=float)
    H_pose = np.empty((d.shape[0], 3, 6))
    H_pose[:, :, :3] = -R.T
    # R_true^T (l - p) = R^T Exp(-dtheta) d ~ R^T (d - dtheta x d) = R^T (d + [d]x dtheta)
    H_pose[:, :, 3:] = np.einsum("ji,njk->nik", R, skew(d))
    return H_pose, R.T.copy()


def init_jacobians(R_world_base: np.ndarray, z_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of the inverse model ``l = p + R z`` for detections (N, 3): ``G_pose`` (N, 3, 6)
    w.r.t. ``[dp_world, dtheta_world]`` and ``G_z`` (3, 3) (= R)."""
    R = np.asarray(R_world_base, dtype=float)
    rz = np.reshape(np.asarray(z_base, dtype=float), (-1, 3)) @ R.T
    G_pose = np.empty((rz.shape[0], 3, 6))
    G_pose[:, :, :3] = np.eye(3)
    # Exp(dtheta) R z ~ R z + dtheta x (R z) = R z - [R z]x dtheta
    G_pose[:, :, 3:] = -skew(rz)
    return G_pose, R.copy()
