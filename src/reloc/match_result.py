"""The answer of the constellation matcher and the covariance of its transform.

``world = scale * R(rotation_rad) @ local + translation``. The covariance comes from the
least-squares geometry of the final inlier fit: residuals ``r_i = s R p_i + t - q_i`` with
Jacobian ``[I2, s dR/dtheta p_i, R p_i]`` over (tx, ty, theta, scale), residual variance
``sigma^2 = sum |r_i|^2 / (2K - 4)``, covariance ``sigma^2 (J^T J)^-1``. A rigid fit (metric maps,
scale held at 1) drops the scale column and has 2K - 3 degrees of freedom.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reloc.geometry import wrap_angle
from reloc.procrustes import Similarity2D, rotation_2d

__all__ = ["MatchResult", "similarity_covariance"]


def similarity_covariance(
    sim: Similarity2D,
    local_xy: np.ndarray,
    world_xy: np.ndarray,
    *,
    floor_sigma_m: float = 0.0,
    with_scale: bool = True,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """(4, 4) covariance of (tx_m, ty_m, theta_rad, scale) of ``sim`` fitted to K >= 3 pairs
    ``local_xy`` (K, 2) -> ``world_xy`` (K, 2); per-axis residual sigma floored at ``floor_sigma_m``.
    ``with_scale=False``: the scale was held at its value (rigid fit); its row/column are zero.
    ``weights`` (K,) in (0, 1]: a weighted fit, pair i with variance sigma^2 / w_i (sigma^2 from
    the weighted residuals: sum w |r|^2 / (2 sum w - n_par), the noise of a pair of weight 1)."""
    p = np.asarray(local_xy, float)
    k = p.shape[0]
    w = np.ones(k) if weights is None else np.asarray(weights, float).reshape(k)
    rot = rotation_2d(sim.theta_rad)
    drot = rot @ np.array([[0.0, -1.0], [1.0, 0.0]])
    res = sim.apply(p) - np.asarray(world_xy, float)
    n_par = 4 if with_scale else 3
    dof = max(2 * float(np.sum(w)) - n_par, 1.0)
    sigma2 = max(float(np.sum(w[:, None] * res * res)) / dof, floor_sigma_m**2)
    jac = np.zeros((k, 2, 4))
    jac[:, 0, 0] = 1.0
    jac[:, 1, 1] = 1.0
    jac[:, :, 2] = sim.scale * p @ drot.T
    jac[:, :, 3] = p @ rot.T
    jtj = np.einsum("k,kia,kib->ab", w, jac[:, :, :n_par], jac[:, :, :n_par])
    cov = np.zeros((4, 4))
    cov[:n_par, :n_par] = sigma2 * np.linalg.inv(jtj)
    return cov


@dataclass(frozen=True)
class MatchResult:
    """A convincing match. ``inlier_pairs`` (K, 2) int: (local index, catalog index).

    ``rmse_m``: RMS inlier distance after the final fit; ``n_local``: local rocks given;
    ``n_hypotheses``: candidate poses generated; ``n_verified``: poses scored;
    ``chance_probability``: probability that a random pose puts one local rock on a catalog rock;
    ``log10_false_alarm``: log10 of (binomial tail of the inlier count x hypotheses tried), the
    acceptance statistic (more negative = more convincing); ``similarity_cov`` (4, 4) over
    (tx_m, ty_m, theta_rad, scale); ``from_guess``: the pose came from verifying the prior's
    guess (tracking), not from the triangle search.
    """

    rotation_rad: float
    translation: np.ndarray
    scale: float
    inlier_pairs: np.ndarray
    rmse_m: float
    n_local: int
    n_hypotheses: int
    n_verified: int
    chance_probability: float
    log10_false_alarm: float
    similarity_cov: np.ndarray
    from_guess: bool = False

    @property
    def n_inliers(self) -> int:
        return int(self.inlier_pairs.shape[0])

    @property
    def rotation(self) -> np.ndarray:
        """(2, 2) rotation world <- local, det +1."""
        return rotation_2d(self.rotation_rad)

    @property
    def T_world_local(self) -> np.ndarray:
        """(3, 3) homogeneous similarity world <- local."""
        out = np.eye(3)
        out[:2, :2] = self.scale * self.rotation
        out[:2, 2] = self.translation
        return out

    @property
    def transform_cov(self) -> np.ndarray:
        """(3, 3) covariance of (tx_m, ty_m, theta_rad), scale marginalised."""
        return self.similarity_cov[:3, :3].copy()

    def apply(self, local_xy: np.ndarray) -> np.ndarray:
        """World positions (N, 2) of local points (N, 2)."""
        return self.scale * np.asarray(local_xy, float) @ self.rotation.T + self.translation

    def pose_in_world(self, local_xy: np.ndarray, local_yaw_rad: float = 0.0) -> tuple[np.ndarray, float]:
        """World (x, y) (2,) and yaw of a body at ``local_xy`` (2,) with heading ``local_yaw_rad``."""
        xy = self.apply(np.asarray(local_xy, float).reshape(1, 2))[0]
        yaw = float(wrap_angle(local_yaw_rad + self.rotation_rad))
        return xy, yaw

    def cov_at(self, local_xy: np.ndarray) -> np.ndarray:
        """(3, 3) covariance of the world (x_m, y_m, yaw_rad) of a body at ``local_xy`` (2,)."""
        p = np.asarray(local_xy, float).reshape(2)
        rot = self.rotation
        drot = rot @ np.array([[0.0, -1.0], [1.0, 0.0]])
        jac = np.zeros((3, 4))
        jac[:2, :2] = np.eye(2)
        jac[:2, 2] = self.scale * drot @ p
        jac[:2, 3] = rot @ p
        jac[2, 2] = 1.0
        cov = jac @ self.similarity_cov @ jac.T
        return 0.5 * (cov + cov.T)
