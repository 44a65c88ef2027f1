"""EKF-SLAM benchmarks: per-step cost against the landmark count, and a long simulated traverse
(real-time factor, ATE without and with global fixes). Pure computation; the CLI prints/saves.

The fixes of the ATE report are *synthetic*: drawn from ground truth plus Gaussian noise and
delivered late, to exercise the fix path without the constellation matcher.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.association import AssociationConfig
from reloc.backend import PoseEstimate
from reloc.geometry import exp_so3, yaw_of
from reloc.landmark_book import LandmarkBookConfig
from reloc.measurements import GlobalFix, ImuSample, RockObservations
from reloc.odometry import OdometryStep

COST_CURVE_N = (0, 25, 50, 100, 200, 300, 500)


@dataclass(frozen=True)
class CostPoint:
    """Median wall time (ms) of one predict and of one landmark frame at ``n_landmarks``."""

    n_landmarks: int
    state_dim: int
    predict_ms: float
    frame_ms: float
    detections_per_frame: int


def _step(t0: float, dt: float, v: float, R0: np.ndarray, w: np.ndarray) -> OdometryStep:
    return OdometryStep(t0, t0 + dt, v, float(w[2]), R0, R0 @ exp_so3(w * dt), w)


def cost_point(n: int, seed: int = 0, n_predict: int = 300, n_frames: int = 15, k_det: int = 15) -> CostPoint:
    """Time predict and a k_det-detection landmark frame with ``n`` landmarks in the state."""
    rng = np.random.default_rng(seed)
    cap = max(n, 1)
    cfg = EkfConfig(
        max_landmarks=cap, landmark_period_s=0.0, attitude_period_s=0.0,
        association=AssociationConfig(max_range_m=40.0),
        book=LandmarkBookConfig(confirm_n_obs=1, confirm_window_s=1e9),
    )
    ekf = EkfSlam(PoseEstimate(0.0, np.eye(4), np.diag([1e-4] * 3 + [1e-6] * 3)), cfg)
    # landmarks on a jittered grid 1.2 m apart (distinct under the gates), half in front
    side = int(np.ceil(np.sqrt(max(n, 1))))
    g = (np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n] - side / 2) * 1.2
    L = np.column_stack([g + rng.uniform(-0.1, 0.1, g.shape), rng.uniform(-0.4, 0.0, n)])
    cov = np.tile(np.diag([0.03, 0.03, 0.03]) ** 2, (n, 1, 1))
    t = 0.0
    if n:
        ekf.observe(RockObservations(t, L, cov, np.full(n, 0.4), np.full(n, 0.9)))
    R = np.eye(3)
    dt = 1.0 / 30.0
    pred = []
    for _ in range(n_predict):
        st = _step(t, dt, 0.0, R, np.zeros(3))
        t0 = time.process_time()
        ekf.predict(st)
        pred.append(time.process_time() - t0)
        t = st.t1
    frames = []
    for _ in range(n_frames if n else 0):
        idx = rng.choice(n, size=min(k_det, n), replace=False)
        z = L[idx] - ekf.estimate().position_m + rng.normal(0, 0.02, (idx.size, 3))
        obs = RockObservations(t, z, cov[idx], np.full(idx.size, 0.4), np.full(idx.size, 0.9))
        t0 = time.process_time()
        ekf.observe(obs)
        frames.append(time.process_time() - t0)
        st = _step(t, dt, 0.0, R, np.zeros(3))
        ekf.predict(st)
        t = st.t1
    return CostPoint(n, ekf.state_vector_size, 1e3 * float(np.median(pred)),
                     1e3 * float(np.median(frames)) if frames else float("nan"), min(k_det, n))


def cost_curve(ns=COST_CURVE_N, seed: int = 0, progress: Callable[[int], None] | None = None) -> list[CostPoint]:
    """:func:`cost_point` for every landmark count in ``ns``."""
    out = []
    for n in ns:
        out.append(cost_point(int(n), seed))
        if progress:
            progress(int(n))
    return out


def synthetic_fixes(gt, t_start: float, period_s: float, latency_s: float, sigma_xy_m: float,
                    sigma_yaw_rad: float, seed: int) -> list[GlobalFix]:
    """Fixes every ``period_s`` from ground truth (a :class:`reloc.backend.Trajectory`) plus noise,
    received ``latency_s`` late (SYNTHETIC: no matcher involved)."""
    rng = np.random.default_rng(seed)
    cov = np.diag([sigma_xy_m**2, sigma_xy_m**2, sigma_yaw_rad**2])
    fixes = []
    for t in np.arange(t_start + period_s, gt.t[-1] - latency_s, period_s):
        k = int(np.searchsorted(gt.t, t))
        T = gt.T_world_base[k]
        fixes.append(GlobalFix(
            t_meas=float(gt.t[k]), t_recv=float(gt.t[k] + latency_s),
            x_m=float(T[0, 3] + rng.normal(0, sigma_xy_m)), y_m=float(T[1, 3] + rng.normal(0, sigma_xy_m)),
            yaw_rad=float(yaw_of(T[:3, :3]) + rng.normal(0, sigma_yaw_rad)), cov_xyyaw=cov))
    return fixes


def run_ekf(initial: PoseEstimate, measurements, config: EkfConfig, fixes: list[GlobalFix] = ()):
    """Run the EKF over ``measurements`` with the runner, each fix delivered at its ``t_recv``;
    returns the filter and the :class:`fgslam.runner.RunResult` (EKF wall and CPU time in
    ``backend_s`` / ``backend_cpu_s``, the fix outcomes in ``outcomes``)."""
    from fgslam.fix_sources import ReplayedFixes
    from fgslam.runner import run_backend

    ekf = EkfSlam(initial, config)
    return ekf, run_backend(ekf, measurements, ReplayedFixes(fixes), time_cpu=True)


def traverse_benchmark(world: str = "my2021", seed: int = 1, duration_s: float = 1000.0, distance_m: float = 66.0,
                       max_landmarks: int = 300, fix_period_s: float = 11.2, fix_latency_s: float = 3.0,
                       fix_sigma_xy_m: float = 0.5, fix_sigma_yaw_deg: float = 2.0) -> dict:
    """Simulate a traverse, run the EKF without and with synthetic late fixes; real-time factor and ATE."""
    from fgslam.metrics import ate
    from sim.config import SimConfig, TraverseConfig
    from sim.simulate import simulate

    t0 = time.perf_counter()
    run = simulate(SimConfig(world=world, seed=seed, traverse=TraverseConfig(distance_m=distance_m, duration_s=duration_s)))
    sim_s = time.perf_counter() - t0
    cfg = EkfConfig(max_landmarks=max_landmarks)
    n_imu = sum(isinstance(m, ImuSample) for m in run.measurements)
    n_frames = sum(isinstance(m, RockObservations) for m in run.measurements)
    sim_duration = float(run.ground_truth.t[-1] - run.ground_truth.t[0])
    out = {"world": world, "seed": seed, "sim_wall_s": sim_s, "duration_s": sim_duration,
           "distance_m": float(run.stats["distance_m"]), "n_imu": n_imu, "n_rock_frames": n_frames,
           "imu_rate_hz": n_imu / sim_duration, "max_landmarks": max_landmarks,
           "config": dataclasses.asdict(cfg)}
    ekf, res = run_ekf(run.initial_pose, run.measurements, cfg)
    wall, cpu = res.backend_s, res.backend_cpu_s
    st = ekf.stats()
    out["no_fixes"] = {"ekf_wall_s": wall, "real_time_factor": sim_duration / wall,
                       "ekf_cpu_s": cpu, "real_time_factor_cpu": sim_duration / cpu,
                       "ate": ate(ekf.trajectory(), run.ground_truth).to_dict(),
                       "n_landmarks_final": st.n_landmarks, "state_dim_final": ekf.state_vector_size,
                       "stats": {k: v for k, v in st.extra.items() if isinstance(v, (int, float))}}
    fixes = synthetic_fixes(run.ground_truth, float(run.ground_truth.t[0]), fix_period_s, fix_latency_s,
                            fix_sigma_xy_m, np.radians(fix_sigma_yaw_deg), seed)
    ekf_f, res_f = run_ekf(run.initial_pose, run.measurements, cfg, fixes)
    wall_f, cpu_f, outcomes = res_f.backend_s, res_f.backend_cpu_s, res_f.outcomes
    out["with_synthetic_fixes"] = {
        "fix_source": "SYNTHETIC: ground truth + N(0, sigma) noise, delivered late",
        "fix_period_s": fix_period_s, "fix_latency_s": fix_latency_s,
        "fix_sigma_xy_m": fix_sigma_xy_m, "fix_sigma_yaw_deg": fix_sigma_yaw_deg,
        "n_fixes": len(fixes), "n_accepted": sum(o.accepted for o in outcomes),
        "reject_reasons": ekf_f.stats().extra["fix_reject_reasons"],
        "ekf_wall_s": wall_f, "real_time_factor": sim_duration / wall_f,
        "ekf_cpu_s": cpu_f, "real_time_factor_cpu": sim_duration / cpu_f,
        "ate": ate(ekf_f.trajectory(), run.ground_truth).to_dict(),
    }
    return out
