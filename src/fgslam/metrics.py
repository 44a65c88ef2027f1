"""Accuracy, relocalization, consistency and runtime metrics (pure numpy, no I/O).

Conventions: trajectories are :class:`reloc.backend.Trajectory` in the world frame; ground truth is
interpolated (linearly in position, unwrapped yaw) at the estimate's stamps. ATE is the 3D
position error in the world frame *without* alignment (the start pose is known), which is what
``evo_ape tum GT EST`` reports with default options; the aligned variant first fits an SE(2)
(rotation about z, translation in x/y) by Kabsch/Umeyama on the x/y positions.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from fgslam.errors import FgslamError
from reloc.backend import Trajectory
from reloc.geometry import wrap_angle, yaw_of

# P(chi2_2 <= x) = 0.9973 (the 3-sigma probability of a 1D Gaussian), for the 2D position ellipse.
CHI2_2DOF_3SIGMA = 11.829158081900795


class MetricsError(FgslamError):
    """Trajectories that cannot be compared (no overlap, too short, bad shapes)."""


def interpolate_truth(gt: Trajectory, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground-truth positions (K, 3) and yaw (K,) at stamps ``t`` (K,), plus the mask of stamps inside gt's span."""
    t = np.asarray(t, dtype=float)
    if len(gt) < 2:
        raise MetricsError(f"ground truth needs at least 2 poses, got {len(gt)}")
    inside = (t >= gt.t[0] - 1e-9) & (t <= gt.t[-1] + 1e-9)
    p = np.stack([np.interp(t, gt.t, gt.positions_m[:, k]) for k in range(3)], axis=1)
    yaw = wrap_angle(np.interp(t, gt.t, np.unwrap(yaw_of(gt.T_world_base))))
    return p, yaw, inside


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a non-negative error sample (metres or radians): RMSE, mean, median, p90, max, n."""

    rmse: float
    mean: float
    median: float
    p90: float
    max: float
    n: int

    @staticmethod
    def of(err: np.ndarray) -> ErrorStats:
        err = np.abs(np.asarray(err, dtype=float))
        if err.size == 0:
            nan = float("nan")
            return ErrorStats(nan, nan, nan, nan, nan, 0)
        return ErrorStats(
            rmse=float(np.sqrt(np.mean(err**2))),
            mean=float(np.mean(err)),
            median=float(np.median(err)),
            p90=float(np.percentile(err, 90)),
            max=float(np.max(err)),
            n=int(err.size),
        )

    def to_dict(self) -> dict:
        return asdict(self)


def umeyama_se2(src_xy: np.ndarray, dst_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid 2D fit dst ~ R @ src + t (Kabsch, det R = +1) for (K, 2) point sets; returns R (2, 2), t (2,)."""
    src_xy, dst_xy = np.asarray(src_xy, float), np.asarray(dst_xy, float)
    if src_xy.shape != dst_xy.shape or src_xy.ndim != 2 or src_xy.shape[1] != 2 or len(src_xy) < 2:
        raise MetricsError(f"umeyama_se2 needs two (K>=2, 2) arrays, got {src_xy.shape} and {dst_xy.shape}")
    mu_s, mu_d = src_xy.mean(0), dst_xy.mean(0)
    H = (src_xy - mu_s).T @ (dst_xy - mu_d)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    return R, mu_d - R @ mu_s


def position_errors(est: Trajectory, gt: Trajectory, align_se2: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per-pose 3D position error vectors (K, 3) (est - truth, world) and the stamps (K,) used."""
    p_gt, _, inside = interpolate_truth(gt, est.t)
    if inside.sum() < 2:
        raise MetricsError("estimate and ground truth do not overlap in time")
    p_est = est.positions_m[inside].copy()
    p_gt = p_gt[inside]
    if align_se2:
        R, t = umeyama_se2(p_est[:, :2], p_gt[:, :2])
        p_est[:, :2] = p_est[:, :2] @ R.T + t
    return p_est - p_gt, est.t[inside]


def ate(est: Trajectory, gt: Trajectory, align_se2: bool = False) -> ErrorStats:
    """Absolute trajectory error (m): statistics of |p_est - p_true| over the estimate's stamps."""
    err, _ = position_errors(est, gt, align_se2)
    return ErrorStats.of(np.linalg.norm(err, axis=1))


def _se3_inv(T: np.ndarray) -> np.ndarray:
    Ti = np.zeros_like(T)
    R = T[..., :3, :3]
    Ti[..., :3, :3] = np.swapaxes(R, -1, -2)
    Ti[..., :3, 3] = -np.einsum("...ji,...j->...i", R, T[..., :3, 3])
    Ti[..., 3, 3] = 1.0
    return Ti


def rpe_per_distance(est: Trajectory, gt: Trajectory, delta_m: float = 10.0) -> ErrorStats:
    """Relative pose error (translation, m) over segments of ``delta_m`` metres travelled (truth).

    For each estimate stamp i, j is the first stamp with travelled distance >= d_i + delta_m; the
    error is the translation of (T_gt_i^-1 T_gt_j)^-1 (T_est_i^-1 T_est_j).
    """
    p_gt, yaw_gt, inside = interpolate_truth(gt, est.t)
    idx = np.flatnonzero(inside)
    if idx.size < 2:
        return ErrorStats.of(np.zeros(0))
    # truth poses as planar-yaw SE(3) at the estimate stamps (z from truth, roll/pitch ignored).
    T_gt = np.tile(np.eye(4), (idx.size, 1, 1))
    c, s = np.cos(yaw_gt[idx]), np.sin(yaw_gt[idx])
    T_gt[:, 0, 0], T_gt[:, 0, 1], T_gt[:, 1, 0], T_gt[:, 1, 1] = c, -s, s, c
    T_gt[:, :3, 3] = p_gt[idx]
    T_est = est.T_world_base[idx].copy()
    ce, se = np.cos(yaw_of(T_est)), np.sin(yaw_of(T_est))
    T_est[:, :3, :3] = 0.0
    T_est[:, 0, 0], T_est[:, 0, 1], T_est[:, 1, 0], T_est[:, 1, 1], T_est[:, 2, 2] = ce, -se, se, ce, 1.0
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p_gt[idx], axis=0), axis=1))])
    j = np.searchsorted(dist, dist + delta_m)
    ok = j < idx.size
    i, j = np.flatnonzero(ok), j[ok]
    if i.size == 0:
        return ErrorStats.of(np.zeros(0))
    rel_gt = _se3_inv(T_gt[i]) @ T_gt[j]
    rel_est = _se3_inv(T_est[i]) @ T_est[j]
    E = _se3_inv(rel_gt) @ rel_est
    return ErrorStats.of(np.linalg.norm(E[:, :3, 3], axis=1))


@dataclass(frozen=True)
class ConsistencyStats:
    """3-sigma consistency of an estimate with covariance against truth.

    ``inside_3sigma``: fraction of stamps whose x/y error lies inside the 3-sigma ellipse
    (NEES_xy <= chi2_2(0.9973)); ``inside_3sigma_axes``: fraction with |e_x| <= 3 sigma_x and
    |e_y| <= 3 sigma_y; ``nees_mean``: average NEES over (x, y, yaw) (3 expected when consistent);
    ``nees_xy_mean``: average over (x, y) (2 expected).
    """

    inside_3sigma: float
    inside_3sigma_axes: float
    nees_mean: float
    nees_xy_mean: float
    n: int

    def to_dict(self) -> dict:
        return asdict(self)


def consistency(est: Trajectory, gt: Trajectory) -> tuple[ConsistencyStats, dict]:
    """Consistency statistics and the per-stamp series (t, err_xy (K,2), err_yaw, sigma_xy (K,2), sigma_yaw, nees_xy).

    Uses the pose covariance convention of reloc.backend (indices 0, 1 = world x, y; 5 = yaw).
    """
    if est.cov is None:
        raise MetricsError("consistency needs an estimate with covariance")
    p_gt, yaw_gt, inside = interpolate_truth(gt, est.t)
    e_xy = est.positions_m[inside, :2] - p_gt[inside, :2]
    e_yaw = wrap_angle(yaw_of(est.T_world_base[inside]) - yaw_gt[inside])
    P = est.cov[inside][:, [0, 1, 5]][:, :, [0, 1, 5]]
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    e3 = np.concatenate([e_xy, e_yaw[:, None]], axis=1)
    nees = np.einsum("ki,ki->k", e3, np.linalg.solve(P, e3[:, :, None])[:, :, 0])
    nees_xy = np.einsum("ki,ki->k", e_xy, np.linalg.solve(P[:, :2, :2], e_xy[:, :, None])[:, :, 0])
    sig = np.sqrt(np.clip(np.diagonal(P, axis1=1, axis2=2), 0.0, None))
    in_axes = np.all(np.abs(e_xy) <= 3.0 * sig[:, :2], axis=1)
    n = int(inside.sum())
    stats = ConsistencyStats(
        inside_3sigma=float(np.mean(nees_xy <= CHI2_2DOF_3SIGMA)) if n else float("nan"),
        inside_3sigma_axes=float(np.mean(in_axes)) if n else float("nan"),
        nees_mean=float(np.mean(nees)) if n else float("nan"),
        nees_xy_mean=float(np.mean(nees_xy)) if n else float("nan"),
        n=n,
    )
    series = {
        "t": est.t[inside],
        "err_xy": e_xy,
        "err_yaw": e_yaw,
        "sigma_xy": sig[:, :2],
        "sigma_yaw": sig[:, 2],
        "nees_xy": nees_xy,
    }
    return stats, series


@dataclass(frozen=True)
class FixStats:
    """Relocalization statistics: attempts, produced and accepted fixes, rates, error distributions.

    Errors compare each fix (x, y, yaw) with the truth at its ``t_meas``; ``within_m`` maps
    threshold (m, as a string key) to the fraction of produced fixes within it.
    """

    attempts: int
    fixes: int
    accepted: int
    rate_hz: float
    accepted_rate_hz: float
    position_error_m: ErrorStats
    yaw_error_rad: ErrorStats
    within_m: dict
    latency_s_mean: float
    nees_mean: float = float("nan")  # fix error NEES over (x, y, yaw) against its covariance (3 if calibrated)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["position_error_m"] = self.position_error_m.to_dict()
        d["yaw_error_rad"] = self.yaw_error_rad.to_dict()
        return d


def fix_errors(fixes_xyyaw: np.ndarray, t_meas: np.ndarray, gt: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Planar position error (K,) m and wrapped yaw error (K,) rad of fixes (K, 3) at ``t_meas`` (K,)."""
    fixes_xyyaw = np.reshape(np.asarray(fixes_xyyaw, float), (-1, 3))
    if fixes_xyyaw.shape[0] == 0:
        return np.zeros(0), np.zeros(0)
    p_gt, yaw_gt, _ = interpolate_truth(gt, t_meas)
    pos = np.linalg.norm(fixes_xyyaw[:, :2] - p_gt[:, :2], axis=1)
    yaw = wrap_angle(fixes_xyyaw[:, 2] - yaw_gt)
    return pos, yaw


def fix_stats(
    n_attempts: int,
    fixes_xyyaw: np.ndarray,
    t_meas: np.ndarray,
    t_recv: np.ndarray,
    accepted: np.ndarray,
    gt: Trajectory | None,
    duration_s: float,
    thresholds_m: tuple[float, ...] = (0.5, 1.0, 2.0),
    cov_xyyaw: np.ndarray | None = None,
) -> FixStats:
    """Summarise the fixes of one run; ``accepted`` (K,) bool says whether the back-end took each fix."""
    fixes_xyyaw = np.reshape(np.asarray(fixes_xyyaw, float), (-1, 3))
    k = fixes_xyyaw.shape[0]
    accepted = np.asarray(accepted, bool).reshape(k)
    if gt is not None and k:
        pos, yaw = fix_errors(fixes_xyyaw, np.asarray(t_meas), gt)
    else:
        pos, yaw = np.zeros(0), np.zeros(0)
    within = {f"{th:g}": (float(np.mean(pos <= th)) if pos.size else float("nan")) for th in thresholds_m}
    nees = float("nan")
    if cov_xyyaw is not None and pos.size:
        p_gt, yaw_gt, _ = interpolate_truth(gt, np.asarray(t_meas))
        e = np.column_stack([fixes_xyyaw[:, :2] - p_gt[:, :2], wrap_angle(fixes_xyyaw[:, 2] - yaw_gt)])
        C = np.reshape(np.asarray(cov_xyyaw, float), (k, 3, 3))
        nees = float(np.mean(np.einsum("ki,ki->k", e, np.linalg.solve(C, e[:, :, None])[:, :, 0])))
    dur = max(float(duration_s), 1e-9)
    lat = np.asarray(t_recv, float) - np.asarray(t_meas, float)
    return FixStats(
        attempts=int(n_attempts),
        fixes=k,
        accepted=int(accepted.sum()),
        rate_hz=k / dur,
        accepted_rate_hz=float(accepted.sum()) / dur,
        position_error_m=ErrorStats.of(pos),
        yaw_error_rad=ErrorStats.of(yaw),
        within_m=within,
        latency_s_mean=float(lat.mean()) if lat.size else float("nan"),
        nees_mean=nees,
    )


def path_length_m(positions_m: np.ndarray) -> float:
    """Length (m) of a polyline of (K, 3) or (K, 2) positions."""
    p = np.asarray(positions_m, float)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def real_time_factor(duration_s: float, wall_s: float) -> float:
    """Simulated seconds processed per wall-clock second."""
    return float(duration_s) / max(float(wall_s), 1e-9)


def improvement_pct(baseline: float, value: float) -> float:
    """ATE improvement (%) of ``value`` over ``baseline``: 100 * (baseline - value) / baseline."""
    return 100.0 * (baseline - value) / baseline if baseline > 0 else float("nan")
