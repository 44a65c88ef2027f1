"""Late global fixes in the smoother: placement, gate, and the record of each fix factor so that
a fix whose residual stays large after optimisation can be retracted."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fgslam.smoother.factors import fix_covariance, fix_residual, make_fix_factor
from reloc.geometry import wrap_angle
from reloc.measurements import GlobalFix


@dataclass
class FixRecord:
    """An applied fix: its factor index in the solver, keyframe, relative motion from the keyframe
    to ``t_meas`` (4, 4) and residual covariance (3, 3)."""

    fix: GlobalFix
    kf: int
    key: int
    T_kf_meas: np.ndarray
    cov: np.ndarray
    factor_index: int
    active: bool = True
    retracted_reason: str = ""


def place_fix(fix: GlobalFix, key: int, T_kf_meas: np.ndarray, cov_rel: np.ndarray,
              T_world_kf: np.ndarray, cauchy_k: float, yaw_sigma_floor_rad: float = 0.0):
    """Factor and residual covariance (3, 3) for ``fix`` attached to keyframe ``key`` through the
    odometry ``T_kf_meas`` (4, 4) with covariance ``cov_rel`` (6, 6, GTSAM body frame); the fix's
    yaw sigma is taken as at least ``yaw_sigma_floor_rad``.

    The odometry part of the covariance is projected with the fix's own heading and the
    estimate's tilt only, so that the factor does not depend on when it arrives (a late fix and
    the same fix on time build the same factor)."""
    T = T_world_kf @ T_kf_meas
    c, s = np.cos(fix.yaw_rad), np.sin(fix.yaw_rad)
    yaw_est = np.arctan2(T[1, 0], T[0, 0])
    ce, se = np.cos(yaw_est), np.sin(yaw_est)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([[ce, se, 0.0], [-se, ce, 0.0], [0.0, 0.0, 1.0]])
    T_proj = np.eye(4)
    T_proj[:3, :3] = Rz @ T[:3, :3]
    cov_fix = np.array(fix.cov_xyyaw, dtype=float)
    if cov_fix[2, 2] < yaw_sigma_floor_rad**2:  # raise the yaw sigma, keep the correlation coefficients
        D = np.diag([1.0, 1.0, yaw_sigma_floor_rad / np.sqrt(cov_fix[2, 2])])
        cov_fix = D @ cov_fix @ D
    cov = fix_covariance(T_proj, cov_rel, cov_fix)
    return make_fix_factor(key, T_kf_meas, fix.xyyaw, cov, cauchy_k), cov


def innovation_d2(fix: GlobalFix, T_world_kf: np.ndarray, cov_kf_body: np.ndarray,
                  T_kf_meas: np.ndarray, cov_res: np.ndarray) -> tuple[float, float]:
    """Squared Mahalanobis distance of the fix against the current estimate (keyframe marginal
    ``cov_kf_body`` (6, 6) included) and the position innovation in metres."""
    r, H = fix_residual(T_world_kf, T_kf_meas, fix.xyyaw)
    S = H @ cov_kf_body @ H.T + cov_res
    return float(r @ np.linalg.solve(S, r)), float(np.hypot(r[0], r[1]))


def residual_d2_many(recs: list[FixRecord], T_world_kf: np.ndarray) -> np.ndarray:
    """Squared whitened residuals (n,) of applied fixes at their keyframes' current estimates
    ``T_world_kf`` (n, 4, 4): the fix factor's residual (:func:`fix_residual`), for all at once."""
    if not recs:
        return np.zeros(0)
    T = np.asarray(T_world_kf, float) @ np.array([r.T_kf_meas for r in recs])
    target = np.array([r.fix.xyyaw for r in recs])
    a = T[:, :3, 0]  # base_link x axis in the world: yaw is its heading on the xy plane
    dyaw = np.arctan2(a[:, 1], a[:, 0]) - target[:, 2]
    r = np.column_stack([T[:, 0, 3] - target[:, 0], T[:, 1, 3] - target[:, 1], wrap_angle(dyaw)])
    w = np.linalg.solve(np.array([rec.cov for rec in recs]), r[:, :, None])[:, :, 0]
    return np.einsum("ij,ij->i", r, w)
