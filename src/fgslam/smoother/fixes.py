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
    """An applied fix (as applied: without its height when that was refused): its factor index in
    the solver, keyframe, relative motion from the keyframe to ``t_meas`` (4, 4) and residual
    covariance (3, 3), or (4, 4) with a height."""

    fix: GlobalFix
    kf: int
    key: int
    T_kf_meas: np.ndarray
    cov: np.ndarray
    factor_index: int
    active: bool = True
    retracted_reason: str = ""
    offset_key: int | None = None  # the source offset the fix measures too (correlation_model "bias")
    offset_rows: np.ndarray | None = None  # (m, 3): how that offset moves the fix's (x, y, yaw[, z])


def place_fix(fix: GlobalFix, key: int, T_kf_meas: np.ndarray, cov_rel: np.ndarray,
              T_world_kf: np.ndarray, cauchy_k: float, yaw_sigma_floor_rad: float = 0.0,
              est_cov_xy: np.ndarray | None = None, kernel_above: float = 0.0,
              offset: tuple[int, np.ndarray] | None = None):
    """Factor and residual covariance (3, 3) for ``fix`` attached to keyframe ``key`` through the
    odometry ``T_kf_meas`` (4, 4) with covariance ``cov_rel`` (6, 6, GTSAM body frame); the fix's
    yaw sigma is taken as at least ``yaw_sigma_floor_rad``. With ``est_cov_xy`` (2, 2, the
    estimate's planar position covariance) the kernel's scale is ``cauchy_k`` in the innovation's
    sigmas (:func:`kernel_scale`, beyond an estimate ``kernel_above`` times as uncertain as the
    fix), else in the fix's. ``offset`` (key, rows (m, 3)): the fix measures its source's offset
    too (:mod:`fgslam.smoother.fix_offsets`; ``fix`` then holds its unshared noise only).

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
    cov_fix = fix.cov
    if cov_fix[2, 2] < yaw_sigma_floor_rad**2:  # raise the yaw sigma, keep the correlation coefficients
        D = np.eye(len(cov_fix))
        D[2, 2] = yaw_sigma_floor_rad / np.sqrt(cov_fix[2, 2])
        cov_fix = D @ cov_fix @ D
    cov = fix_covariance(T_proj, cov_rel, cov_fix)
    k = cauchy_k if est_cov_xy is None else cauchy_k * kernel_scale(est_cov_xy, cov[:2, :2], kernel_above)
    okey, rows = offset if offset is not None else (None, None)
    return make_fix_factor(key, T_kf_meas, fix.measured, cov, k, okey, rows), cov


@dataclass(frozen=True)
class Innovation:
    """A fix against the current estimate: ``d2`` the squared Mahalanobis distance of its planar
    part, ``distance_m`` the position innovation, ``height_d2`` that of its height alone (None
    without one)."""

    d2: float
    distance_m: float
    height_d2: float | None = None


def kernel_scale(cov_est_xy: np.ndarray, cov_fix_xy: np.ndarray, above: float = 0.0) -> float:
    """How much wider than the fix's own position sigmas the innovation's spread (the estimate's
    ``cov_est_xy`` (2, 2) plus the fix's ``cov_fix_xy``) is, in the direction where it is most,
    beyond the spread of an estimate ``above`` times as uncertain as the fix:
    ``max(1, sqrt((1 + lambda_max(cov_fix_xy^-1 cov_est_xy)) / (1 + above^2)))`` (``above`` 0: the
    whole ratio). From covariances alone, so a fix's factor is the same whenever it arrives; 1 when
    ``cov_fix_xy`` is not positive definite."""
    try:
        Li = np.linalg.inv(np.linalg.cholesky(np.asarray(cov_fix_xy, dtype=float)))
    except np.linalg.LinAlgError:
        return 1.0
    lam = float(np.linalg.eigvalsh(Li @ np.asarray(cov_est_xy, dtype=float) @ Li.T)[-1])
    if not np.isfinite(lam):
        return 1.0
    return float(max(1.0, np.sqrt((1.0 + max(lam, 0.0)) / (1.0 + above**2))))


def innovation_d2(fix: GlobalFix, T_world_kf: np.ndarray, cov_kf_body: np.ndarray,
                  T_kf_meas: np.ndarray, cov_res: np.ndarray, shift: np.ndarray | None = None,
                  shift_cov: np.ndarray | None = None) -> Innovation:
    """The fix's innovation against the current estimate (keyframe marginal ``cov_kf_body`` (6, 6)
    included; ``cov_res`` the residual covariance of :func:`place_fix`); with a source offset, its
    predicted effect ``shift`` (m,) on the fix and that effect's covariance ``shift_cov`` (m, m)
    (taken as independent of the pose's)."""
    r, H = fix_residual(T_world_kf, T_kf_meas, fix.measured)
    S = H @ cov_kf_body @ H.T + cov_res
    if shift is not None:
        r = r + shift
        S = S + shift_cov
    d2 = float(r[:3] @ np.linalg.solve(S[:3, :3], r[:3]))
    return Innovation(d2, float(np.hypot(r[0], r[1])), float(r[3] ** 2 / S[3, 3]) if len(r) == 4 else None)


def residual_d2_many(recs: list[FixRecord], T_world_kf: np.ndarray, offsets: list | None = None) -> np.ndarray:
    """Squared whitened residuals (n,) of applied fixes at their keyframes' current estimates
    ``T_world_kf`` (n, 4, 4): the fix factor's residual (:func:`fix_residual`), for all at once
    (a fix without a height gets a zero z residual of unit variance, which adds nothing). With
    ``offsets`` (n: each fix's source offset estimate (3,), or None) the residual holds the offset
    as the factor does."""
    if not recs:
        return np.zeros(0)
    T = np.asarray(T_world_kf, float) @ np.array([r.T_kf_meas for r in recs])
    target = np.array([r.fix.xyyaw for r in recs])
    a = T[:, :3, 0]  # base_link x axis in the world: yaw is its heading on the xy plane
    dyaw = np.arctan2(a[:, 1], a[:, 0]) - target[:, 2]
    z = np.array([np.nan if r.fix.height is None else r.fix.height.z_m for r in recs])
    dz = np.where(np.isnan(z), 0.0, T[:, 2, 3] - np.nan_to_num(z))
    r = np.column_stack([T[:, 0, 3] - target[:, 0], T[:, 1, 3] - target[:, 1], wrap_angle(dyaw), dz])
    for i, o in enumerate(offsets or ()):
        if o is not None:
            G = recs[i].offset_rows
            r[i, :len(G)] += G @ o
    C = np.tile(np.eye(4), (len(recs), 1, 1))
    for i, rec in enumerate(recs):
        n = len(rec.cov)
        C[i, :n, :n] = rec.cov
    w = np.linalg.solve(C, r[:, :, None])[:, :, 0]
    return np.einsum("ij,ij->i", r, w)
