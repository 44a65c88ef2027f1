"""A small seeded synthetic rover world for tests and benchmarks (no rendering): rolling terrain,
random rocks, a rover steered to stay in its yard, noisy command speed (slip), an IMU whose yaw
drifts, stereo rock detections whose depth noise grows with range squared, and late global fixes
synthesised from ground truth. Produces the same typed measurements as the simulator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from reloc.backend import PoseEstimate
from reloc.measurements import (
    CmdVel,
    GlobalFix,
    GroundTruthPose,
    ImuSample,
    RockObservations,
    sort_key,
)


@dataclass(frozen=True)
class SyntheticConfig:
    """Seeded synthetic traverse."""

    seed: int = 0
    duration_s: float = 300.0
    speed_mps: float = 0.15
    yard_radius_m: float = 20.0
    hill_amplitude_m: float = 1.0
    rock_density_per_m2: float = 0.08
    imu_rate_hz: float = 30.0
    rock_rate_hz: float = 5.0
    max_range_m: float = 8.0
    fov_rad: float = 1.2
    sigma_px_rad: float = 0.002  # bearing noise of the stereo rig
    sigma_depth_coef: float = 0.01  # depth sigma = coef * range^2 (m)
    slip_sigma: float = 0.05  # true speed = cmd * (1 + slip), slip varying every few seconds
    gyro_bias_radps: float = 2e-4  # yaw drift of the IMU reference
    imu_att_sigma_rad: float = 0.002


@dataclass
class SyntheticRun:
    """Sorted measurements, ground truth ``t`` (K,), ``T_world_base`` (K, 4, 4), rocks (R, 3), start pose."""

    measurements: list
    gt_t: np.ndarray
    gt_T: np.ndarray
    rocks_world_m: np.ndarray
    initial_pose: PoseEstimate

    def gt_at(self, t: float) -> np.ndarray:
        """Ground-truth pose (4, 4) at the sample nearest ``t``."""
        i = int(np.clip(np.searchsorted(self.gt_t, t), 0, len(self.gt_t) - 1))
        return self.gt_T[i]


def _height(cfg: SyntheticConfig, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, k = cfg.hill_amplitude_m, 2 * np.pi / 25.0
    x, y = xy[..., 0], xy[..., 1]
    h = a * np.sin(k * x) * np.cos(0.7 * k * y)
    grad = np.stack([a * k * np.cos(k * x) * np.cos(0.7 * k * y), -0.7 * a * k * np.sin(k * x) * np.sin(0.7 * k * y)], -1)
    return h, grad


def _attitude(yaw: float, grad: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    xb = np.array([c, s, grad[0] * c + grad[1] * s])
    xb /= np.linalg.norm(xb)
    n = np.array([-grad[0], -grad[1], 1.0])
    yb = np.cross(n, xb)
    yb /= np.linalg.norm(yb)
    return np.column_stack([xb, yb, np.cross(xb, yb)])


def simulate_synthetic(cfg: SyntheticConfig) -> SyntheticRun:
    """Generate one seeded run (see module doc)."""
    rng = np.random.default_rng(cfg.seed)
    dt = 1.0 / cfg.imu_rate_hz
    n = int(cfg.duration_s * cfg.imu_rate_hz) + 1
    xy, yaw, w_cmd = np.zeros(2), 0.0, 0.0
    slip, drift = 0.0, 0.0
    meas: list = []
    gt_t, gt_T = np.zeros(n), np.zeros((n, 4, 4))
    frame_every = max(1, round(cfg.imu_rate_hz / cfg.rock_rate_hz))
    T_list = []
    for i in range(n):
        t = i * dt
        if i % int(cfg.imu_rate_hz * 4) == 0:
            slip = rng.normal(0.0, cfg.slip_sigma)
            w_cmd = rng.normal(0.0, 0.05)
            if np.linalg.norm(xy) > cfg.yard_radius_m:
                home = np.arctan2(-xy[1], -xy[0])
                w_cmd = float(np.clip(np.angle(np.exp(1j * (home - yaw))) / 4.0, -0.3, 0.3))
        if i % int(cfg.imu_rate_hz) == 0:
            meas.append(CmdVel(t, cfg.speed_mps, w_cmd))
        h, grad = _height(cfg, xy)
        R = _attitude(yaw, grad)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, [xy[0], xy[1], float(h)]
        gt_t[i], gt_T[i] = t, T
        T_list.append(T)
        drift += cfg.gyro_bias_radps * dt
        R_imu = Rotation.from_rotvec([0, 0, drift]).as_matrix() @ R
        R_imu = Rotation.from_rotvec(rng.normal(0, cfg.imu_att_sigma_rad, 3)).as_matrix() @ R_imu
        meas.append(ImuSample(t, Rotation.from_matrix(R_imu).as_quat()))
        meas.append(GroundTruthPose(t, T[:3, 3], Rotation.from_matrix(R).as_quat()))
        # true motion to the next sample: yaw from the commanded rate (the IMU sees it), speed with slip
        v3 = cfg.speed_mps * (1.0 + slip)
        slope = grad[0] * np.cos(yaw) + grad[1] * np.sin(yaw)
        v_plan = v3 / np.sqrt(1.0 + slope**2)
        xy = xy + v_plan * dt * np.array([np.cos(yaw), np.sin(yaw)])
        yaw += w_cmd * dt
    # rocks in the area driven through
    lo, hi = gt_T[:, :2, 3].min(0) - 10.0, gt_T[:, :2, 3].max(0) + 10.0
    n_rocks = int(cfg.rock_density_per_m2 * np.prod(hi - lo))
    rxy = rng.uniform(lo, hi, (n_rocks, 2))
    path_tree = cKDTree(gt_T[::30, :2, 3])
    rxy = rxy[path_tree.query(rxy)[0] < cfg.max_range_m + 2.0]
    rocks = np.column_stack([rxy, _height(cfg, rxy)[0] + 0.1])
    sizes = rng.uniform(0.15, 0.6, len(rocks))
    tree = cKDTree(rocks[:, :2])
    for i in range(0, n, frame_every):
        T = gt_T[i]
        idx = tree.query_ball_point(T[:2, 3], cfg.max_range_m)
        z = (rocks[idx] - T[:3, 3]) @ T[:3, :3]
        keep = (z[:, 0] > 0.5) & (np.abs(np.arctan2(z[:, 1], z[:, 0])) < cfg.fov_rad / 2)
        keep &= rng.uniform(size=len(z)) < 0.9  # missed detections
        z, sz = z[keep], sizes[np.asarray(idx, dtype=int)[keep]] if len(idx) else np.zeros(0)
        covs = []
        for zi in z:
            r = np.linalg.norm(zi)
            u = zi / r
            sig = np.array([cfg.sigma_depth_coef * r**2 + 0.01, cfg.sigma_px_rad * r + 0.005, cfg.sigma_px_rad * r + 0.005])
            B = np.column_stack([u, np.cross([0, 0, 1.0], u) / max(np.linalg.norm(np.cross([0, 0, 1.0], u)), 1e-9)])
            B = np.column_stack([B, np.cross(B[:, 0], B[:, 1])])
            covs.append(B @ np.diag(sig**2) @ B.T)
        covs = np.array(covs).reshape(-1, 3, 3)
        noisy = np.array([rng.multivariate_normal(zi, C) for zi, C in zip(z, covs)]).reshape(-1, 3)
        meas.append(RockObservations(gt_t[i], noisy, covs, sz * rng.uniform(0.8, 1.2, len(sz)), np.full(len(sz), 0.9)))
    meas.sort(key=sort_key)
    cov0 = np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5])
    return SyntheticRun(meas, gt_t, gt_T, rocks, PoseEstimate(0.0, gt_T[0].copy(), cov0))


def synthetic_fixes(
    run: SyntheticRun,
    rng: np.random.Generator,
    period_s: float = 11.0,
    delay_s: tuple[float, float] = (1.0, 30.0),
    sigma_xy_m: float = 0.5,
    sigma_yaw_rad: float = 0.03,
    wrong_fraction: float = 0.0,
    wrong_offset_m: tuple[float, float] = (5.0, 20.0),
    wrong_mode: str = "add",
) -> list[tuple[GlobalFix, bool]]:
    """Fixes every ``period_s`` from ground truth + noise, delivered 1-30 s late, and wrong ones
    offset by 5-20 m in a random direction: ``wrong_mode`` "add" injects extra wrong fixes (half-way
    between good ones) so that they make up ``wrong_fraction`` of the stream, "replace" corrupts
    that fraction of the good ones. The good fixes are the same draws in every mode. Returns
    (fix, is_wrong) sorted by ``t_recv``."""
    if wrong_mode not in ("add", "replace"):
        raise ValueError(f"wrong_mode must be 'add' or 'replace', got {wrong_mode!r}")
    t_end = run.gt_t[-1]
    times = np.arange(period_s, t_end - delay_s[1], period_s)
    draws = [(rng.normal(0, sigma_xy_m, 2), rng.normal(0, sigma_yaw_rad), rng.uniform(*delay_s)) for _ in times]
    wrong_rng = np.random.default_rng(rng.integers(2**31))
    n_wrong = round(wrong_fraction * len(times) / ((1.0 - wrong_fraction) if wrong_mode == "add" else 1.0))
    if wrong_mode == "add":
        slots = wrong_rng.choice(len(times), size=min(n_wrong, len(times)), replace=False)
        specs = [(t, d, False) for t, d in zip(times, draws)]
        specs += [(times[i] + period_s / 2, draws[i], True) for i in slots]
    else:
        bad = set(wrong_rng.choice(len(times), size=min(n_wrong, len(times)), replace=False).tolist())
        specs = [(t, d, i in bad) for i, (t, d) in enumerate(zip(times, draws))]
    out = []
    cov = np.diag([sigma_xy_m**2, sigma_xy_m**2, sigma_yaw_rad**2])
    for t, (dxy, dyaw, delay), wrong in specs:
        T = run.gt_at(t)
        xy = T[:2, 3] + dxy
        if wrong:
            a = wrong_rng.uniform(0, 2 * np.pi)
            xy = xy + wrong_rng.uniform(*wrong_offset_m) * np.array([np.cos(a), np.sin(a)])
        yaw = np.arctan2(T[1, 0], T[0, 0]) + dyaw
        out.append((GlobalFix(t, t + delay, xy[0], xy[1], yaw, cov, n_inliers=8, rmse_m=0.3), wrong))
    out.sort(key=lambda fw: fw[0].t_recv)
    return out


@dataclass
class DriveResult:
    """Outcome of :func:`drive`: per-fix outcomes, causal estimates sampled at ``sample_hz``, wall time."""

    outcomes: list
    est_t: np.ndarray
    est_T: np.ndarray
    est_cov: np.ndarray
    wall_s: float
    backend_s: float  # wall time spent inside the back-end's methods
    backend_cpu_s: float  # CPU time of the same


def drive(backend, measurements: list, fixes: list[GlobalFix] = (), sample_hz: float = 1.0,
          progress=None, hold=None) -> DriveResult:
    """Run a back-end over a sorted measurement stream with the runner (:func:`fgslam.runner.run_backend`),
    each fix delivered when the stream reaches its ``t_recv``; the causal estimate recorded at
    ``sample_hz``; ``progress(t)`` called as the runner reports progress. ``hold``: the runner's
    :class:`fgslam.fix_hold.FixHoldConfig` (None: off, every fix reaches the back-end's own gates)."""
    from fgslam.fix_hold import FixHoldConfig
    from fgslam.fix_sources import ReplayedFixes
    from fgslam.runner import RunnerConfig, run_backend

    cfg = RunnerConfig(record_rate_hz=sample_hz, fix_hold=hold if hold is not None else FixHoldConfig(beyond_m=0.0))
    res = run_backend(backend, measurements, ReplayedFixes(fixes), config=cfg, on_progress=progress, time_cpu=True)
    on = res.online
    return DriveResult(res.outcomes, on.t, on.T_world_base, on.cov, res.wall_s, res.backend_s, res.backend_cpu_s)


def ate_m(run: SyntheticRun, t: np.ndarray, T: np.ndarray) -> float:
    """Absolute trajectory error (RMSE of 3D positions, m) of poses (K, 4, 4) at times (K,) against
    ground truth; no alignment (the world frame is known)."""
    gt = np.array([run.gt_at(ti)[:3, 3] for ti in t])
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - gt) ** 2, axis=1))))
