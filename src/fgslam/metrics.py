"""Accuracy, relocalization, consistency and runtime metrics (pure numpy, no I/O).

Conventions: trajectories are :class:`reloc.backend.Trajectory` in the world frame; ground truth is
interpolated (linearly in position, unwrapped yaw) at the estimate's stamps. ATE is the 3D
position error in the world frame *without* alignment (the start pose is known), which is what
``evo_ape tum GT EST`` reports with default options; the aligned variant first fits an SE(2)
(rotation about z, translation in x/y) by Kabsch/Umeyama on the x/y positions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from fgslam.errors import FgslamError
from fgslam.nees import NeesTest, whiten, whitened_test
from reloc.backend import PLANAR_POSE_INDICES, Trajectory
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


def ate_parts(est: Trajectory, gt: Trajectory) -> tuple[ErrorStats, ErrorStats]:
    """The ATE's two parts: planar (|(x, y) error|, what a fix corrects) and height (|z error|,
    which planar fixes leave free), each over the estimate's stamps (m)."""
    err, _ = position_errors(est, gt)
    return ErrorStats.of(np.linalg.norm(err[:, :2], axis=1)), ErrorStats.of(np.abs(err[:, 2]))


def _se3_inv(T: np.ndarray) -> np.ndarray:
    Ti = np.zeros_like(T)
    R = T[..., :3, :3]
    Ti[..., :3, :3] = np.swapaxes(R, -1, -2)
    Ti[..., :3, 3] = -np.einsum("...ji,...j->...i", R, T[..., :3, 3])
    Ti[..., 3, 3] = 1.0
    return Ti


def associate_stamps(t_a: np.ndarray, t_b: np.ndarray, max_diff_s: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ia, ib) of nearest stamps within ``max_diff_s``, as evo's ``associate_trajectories``
    (nearest_time) pairs them: each stamp of the shorter series (a on ties) with its nearest in the
    other (the later one when both are equally near and within reach); both ascending."""
    t_a, t_b = np.asarray(t_a, float), np.asarray(t_b, float)
    swap = len(t_b) < len(t_a)  # evo starts from the trajectory with fewer poses
    s, l = (t_b, t_a) if swap else (t_a, t_b)
    if s.size == 0 or l.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    i_s = np.flatnonzero((s >= l[0] - max_diff_s) & (s <= l[-1] + max_diff_s))
    up = np.minimum(np.searchsorted(l, s[i_s], side="right"), l.size - 1)
    d_ub = l[up] - s[i_s]
    d_lb = np.where(up > 0, s[i_s] - l[np.maximum(up - 1, 0)], np.inf)
    take_ub = (d_ub <= max_diff_s) & (d_ub < d_lb)
    take_lb = ~take_ub & (d_lb <= max_diff_s) & (d_lb <= d_ub)
    keep = take_ub | take_lb
    i_l = np.where(take_ub, up, up - 1)[keep]
    i_s = i_s[keep]
    return (i_l, i_s) if swap else (i_s, i_l)


def _pairs(T: np.ndarray, delta: float, unit: str) -> tuple[np.ndarray, np.ndarray]:
    """evo's consecutive pairs: every ``delta`` frames, or each time ``delta`` metres of path (of
    these poses) have been travelled since the previous pair's end."""
    if unit == "frames":
        ids = np.arange(0, len(T), int(delta))
        return ids[:-1], ids[1:]
    if unit != "m":
        raise MetricsError(f"RPE delta unit must be 'm' or 'frames', got {unit!r}")
    step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    ids, acc = [0], 0.0
    for k, d in enumerate(step.tolist(), start=1):  # a running sum that restarts: sequential by nature
        acc += d
        if acc >= delta:
            ids.append(k)
            acc = 0.0
    ids = np.asarray(ids)
    return ids[:-1], ids[1:]


def rpe(est: Trajectory, gt: Trajectory, delta: float = 10.0, unit: str = "m", max_diff_s: float = 0.01) -> ErrorStats:
    """Relative pose error, translation part (m), as ``evo_rpe tum GT EST --delta D --delta_unit
    {m,f}`` computes it with its defaults: stamps associated within ``max_diff_s`` (no
    interpolation), consecutive pairs (i, j) taken on the *estimate's* path every ``delta`` metres
    (``unit`` "m") or frames ("frames"), error E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) on full SE(3) poses
    (Q truth, P estimate), statistic of |translation(E)|."""
    if not delta > 0:
        raise MetricsError(f"RPE delta must be > 0, got {delta}")
    ie, ig = associate_stamps(est.t, gt.t, max_diff_s)
    if ie.size < 2:
        raise MetricsError(f"estimate and ground truth share fewer than 2 stamps within {max_diff_s} s")
    P, Q = est.T_world_base[ie], gt.T_world_base[ig]
    i, j = _pairs(P, delta, unit)
    if i.size == 0:
        return ErrorStats.of(np.zeros(0))
    E = _se3_inv(_se3_inv(Q[i]) @ Q[j]) @ (_se3_inv(P[i]) @ P[j])
    return ErrorStats.of(np.linalg.norm(E[:, :3, 3], axis=1))


@dataclass(frozen=True)
class ConsistencyStats:
    """Consistency of an estimate with covariance against truth.

    One-sided, as a band check: ``inside_3sigma`` is the fraction of stamps whose x/y error lies
    inside the 3-sigma ellipse (NEES_xy <= chi2_2(0.9973)); ``inside_3sigma_axes`` the fraction with
    |e_x| <= 3 sigma_x and |e_y| <= 3 sigma_y. Two-sided (:mod:`fgslam.nees`): ``position`` tests the
    mean NEES of the (x, y) error (2 dof), ``yaw`` of the yaw error (1 dof), ``pose`` of (x, y, yaw)
    (3 dof), each against its 95 % chi-square interval for the run's effective sample size, and
    ``height`` of the z error against its own sigma (1 dof: the height a planar fix leaves to the
    odometry, the landmarks and the terrain model's heights, outside the planar tests).
    ``nees_mean`` / ``nees_xy_mean`` repeat the pose / position means.
    """

    inside_3sigma: float
    inside_3sigma_axes: float
    nees_mean: float
    nees_xy_mean: float
    n: int
    position: NeesTest
    yaw: NeesTest
    pose: NeesTest
    height: NeesTest

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("position", "yaw", "pose", "height"):
            d[k] = getattr(self, k).to_dict()
        return d


def consistency(est: Trajectory, gt: Trajectory) -> tuple[ConsistencyStats, dict]:
    """Consistency statistics and the per-stamp series (t, err_xy (K,2), err_z, err_yaw, sigma_xy
    (K,2), sigma_z, sigma_yaw, nees_xy, nees_yaw, nees). The NEES are planar (x, y, yaw: what a
    fix corrects); the height's error and sigma come beside them.

    Uses the pose covariance convention of reloc.backend (indices 0, 1 = world x, y; 5 = yaw).
    """
    if est.cov is None:
        raise MetricsError("consistency needs an estimate with covariance")
    p_gt, yaw_gt, inside = interpolate_truth(gt, est.t)
    e_xy = est.positions_m[inside, :2] - p_gt[inside, :2]
    e_z = est.positions_m[inside, 2] - p_gt[inside, 2]
    e_yaw = wrap_angle(yaw_of(est.T_world_base[inside]) - yaw_gt[inside])
    C = est.cov[inside]
    i = list(PLANAR_POSE_INDICES)
    P = C[:, i][:, :, i]
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    e3 = np.concatenate([e_xy, e_yaw[:, None]], axis=1)
    w3, w_xy, w_yaw = whiten(e3, P), whiten(e_xy, P[:, :2, :2]), whiten(e_yaw, P[:, 2, 2])
    w_z = whiten(e_z, C[:, 2, 2])
    nees, nees_xy, nees_yaw = (np.einsum("ki,ki->k", w, w) for w in (w3, w_xy, w_yaw))
    sig = np.sqrt(np.clip(np.diagonal(P, axis1=1, axis2=2), 0.0, None))
    in_axes = np.all(np.abs(e_xy) <= 3.0 * sig[:, :2], axis=1)
    n = int(inside.sum())
    nan = float("nan")
    stats = ConsistencyStats(
        inside_3sigma=float(np.mean(nees_xy <= CHI2_2DOF_3SIGMA)) if n else nan,
        inside_3sigma_axes=float(np.mean(in_axes)) if n else nan,
        nees_mean=float(np.nanmean(nees)) if np.isfinite(nees).any() else nan,
        nees_xy_mean=float(np.nanmean(nees_xy)) if np.isfinite(nees_xy).any() else nan,
        n=n,
        position=whitened_test(w_xy),
        yaw=whitened_test(w_yaw),
        pose=whitened_test(w3),
        height=whitened_test(w_z),
    )
    series = {
        "t": est.t[inside],
        "err_xy": e_xy,
        "err_z": e_z,
        "err_yaw": e_yaw,
        "sigma_xy": sig[:, :2],
        "sigma_z": np.sqrt(np.clip(C[:, 2, 2], 0.0, None)),
        "sigma_yaw": sig[:, 2],
        "nees_xy": nees_xy,
        "nees_yaw": nees_yaw,
        "nees": nees,
        "white_xy": w_xy,
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
    # fix error NEES over (x, y, yaw) against the covariance sent (3 if calibrated and the fixes
    # independent; a producer that scales it for the fixes' correlation makes it smaller by design)
    nees_mean: float = float("nan")
    # two-sided test of each fix against its covariance alone (before the producer's correlation
    # factor, GlobalFix.split_cov): whether the matcher's claimed error is the error it makes
    nees_alone: NeesTest | None = None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["position_error_m"] = self.position_error_m.to_dict()
        d["yaw_error_rad"] = self.yaw_error_rad.to_dict()
        d["nees_alone"] = None if self.nees_alone is None else self.nees_alone.to_dict()
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


def fix_height_stats(fixes: Sequence, gt: Trajectory | None) -> dict:
    """The fixes that carry a height (:class:`reloc.measurements.FixHeight`): how many, and with
    truth the RMSE of their z against the truth's at ``t_meas`` and their mean NEES (1 dof)."""
    hs = [f for f in fixes if f.height is not None]
    out: dict = {"n": len(hs)}
    if not hs or gt is None:
        return out
    p_gt, _, _ = interpolate_truth(gt, np.array([f.t_meas for f in hs]))
    e = np.array([f.height.z_m for f in hs]) - p_gt[:, 2]
    var = np.array([f.height.var_m2 for f in hs])
    out.update({"error_rmse_m": float(np.sqrt(np.mean(e**2))), "error_mean_m": float(np.mean(e)),
                "nees": float(np.mean(e**2 / var)), "sigma_median_m": float(np.median(np.sqrt(var)))})
    return out


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
    cov_alone_xyyaw: np.ndarray | None = None,
) -> FixStats:
    """Summarise the fixes of one run; ``accepted`` (K,) bool says whether the back-end took each
    fix. ``cov_xyyaw`` (K, 3, 3): the covariances sent (``nees_mean``); ``cov_alone_xyyaw``: each
    fix's own, before a correlation factor (``nees_alone``, a two-sided test over the fixes in
    order, their shared catalog error counted in the effective sample size)."""
    fixes_xyyaw = np.reshape(np.asarray(fixes_xyyaw, float), (-1, 3))
    k = fixes_xyyaw.shape[0]
    accepted = np.asarray(accepted, bool).reshape(k)
    if gt is not None and k:
        pos, yaw = fix_errors(fixes_xyyaw, np.asarray(t_meas), gt)
    else:
        pos, yaw = np.zeros(0), np.zeros(0)
    within = {f"{th:g}": (float(np.mean(pos <= th)) if pos.size else float("nan")) for th in thresholds_m}
    nees, alone = float("nan"), None
    if (cov_xyyaw is not None or cov_alone_xyyaw is not None) and pos.size:
        p_gt, yaw_gt, _ = interpolate_truth(gt, np.asarray(t_meas))
        e = np.column_stack([fixes_xyyaw[:, :2] - p_gt[:, :2], wrap_angle(fixes_xyyaw[:, 2] - yaw_gt)])
        if cov_xyyaw is not None:
            C = np.reshape(np.asarray(cov_xyyaw, float), (k, 3, 3))
            nees = float(np.mean(np.einsum("ki,ki->k", e, np.linalg.solve(C, e[:, :, None])[:, :, 0])))
        if cov_alone_xyyaw is not None:
            alone = whitened_test(whiten(e, np.reshape(np.asarray(cov_alone_xyyaw, float), (k, 3, 3))))
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
        nees_alone=alone,
    )


def error_along(est: Trajectory, gt: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """(distance the truth has travelled at each of the estimate's stamps (K,) m, planar position
    error there (K,) m), over the stamps inside the truth's span."""
    p_gt, _, inside = interpolate_truth(gt, est.t)
    d_gt = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt.positions_m[:, :2], axis=0), axis=1))])
    dist = np.interp(est.t[inside], gt.t, d_gt)
    return dist, np.linalg.norm(est.positions_m[inside, :2] - p_gt[inside, :2], axis=1)


def drift_pct(est: Trajectory, gt: Trajectory) -> float:
    """Final planar position error as a percentage of the distance travelled (truth)."""
    dist, err = error_along(est, gt)
    return 100.0 * float(err[-1]) / float(dist[-1]) if len(dist) and dist[-1] > 0 else float("nan")


def error_by_distance(est: Trajectory, gt: Trajectory, step_m: float) -> list[dict]:
    """Planar error statistics per ``step_m`` of distance travelled: one dict per bin with its end
    distance (m), RMSE and max (m); for the error-against-distance tables of long traverses."""
    if not step_m > 0:
        raise MetricsError(f"error_by_distance step_m must be > 0, got {step_m}")
    dist, err = error_along(est, gt)
    if not len(dist):
        return []
    k = np.maximum(np.ceil(dist / step_m - 1e-9).astype(int) - 1, 0)  # bins (b step, (b + 1) step]
    return [{"to_m": float(min((b + 1) * step_m, dist[-1])), "rmse_m": float(np.sqrt(np.mean(err[k == b] ** 2))),
             "max_m": float(err[k == b].max())} for b in np.unique(k)]


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
