"""A small seeded synthetic world for EKF unit tests: gently sloped ground, random rocks, noisy
command speed and IMU, stereo noise growing with range squared. The truth is drawn from the
filter's own process-noise model, so a consistent filter must pass chi-square checks on it."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ekf.config import MotionNoiseConfig
from ekf.motion import process_noise_body
from reloc.geometry import exp_so3, log_so3
from reloc.measurements import GroundTruthPose, RockObservations
from reloc.odometry import OdometryStep


@dataclass
class SynthRun:
    steps: list  # OdometryStep per IMU interval
    frames: dict  # IMU index -> RockObservations taken at the end of that step
    truth_p: np.ndarray  # (K+1, 3)
    truth_R: np.ndarray  # (K+1, 3, 3)
    t: np.ndarray  # (K+1,)
    rocks: np.ndarray  # (M, 3)


def stereo_cov(z_base: np.ndarray) -> np.ndarray:
    """(N, 3, 3) covariance: depth sigma 0.02 + 0.004 r^2 m along the ray, 0.01 + 0.003 r across."""
    out = np.empty((len(z_base), 3, 3))
    for i, z in enumerate(z_base):
        r = np.linalg.norm(z)
        u = z / r
        a = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        v = np.cross(u, a)
        v /= np.linalg.norm(v)
        w = np.cross(u, v)
        U = np.column_stack([u, v, w])
        s = np.array([0.02 + 0.004 * r * r, 0.01 + 0.003 * r, 0.01 + 0.003 * r])
        out[i] = (U * s**2) @ U.T
    return out


def simulate(seed: int, duration_s: float = 60.0, rate_hz: float = 30.0, frame_every: int = 6,
             n_rocks: int = 250, noise: MotionNoiseConfig | None = None) -> SynthRun:
    noise = noise or MotionNoiseConfig()
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    K = round(duration_s * rate_hz)
    t = np.arange(K + 1) * dt
    p = np.zeros((K + 1, 3))
    R = np.zeros((K + 1, 3, 3))
    R[0] = np.eye(3)
    R_imu = np.eye(3)
    v_cmd = 0.25
    yaw_rate = 0.0
    steps = []
    for k in range(K):
        if k % int(5 * rate_hz) == 0:
            yaw_rate = rng.uniform(-0.08, 0.08)
        w_true = np.array([0.03 * np.sin(0.7 * t[k]), 0.03 * np.cos(0.5 * t[k]), yaw_rate])
        dR_true = exp_so3(w_true * dt)
        R[k + 1] = R[k] @ dR_true
        # IMU: roll/pitch gravity-referenced, yaw drifting by a random walk
        probe = OdometryStep(t[k], t[k + 1], v_cmd, yaw_rate, R[k], R[k + 1], w_true)
        var_t, var_r = process_noise_body(probe, noise)
        R_imu_next = exp_so3(np.array([0.0, 0.0, rng.normal(0.0, np.sqrt(var_r[2]))])) @ R_imu @ dR_true
        R_mid = R[k] @ exp_so3(0.5 * log_so3(dR_true))
        d_body = np.array([v_cmd * dt, 0.0, 0.0]) + rng.normal(0.0, np.sqrt(var_t))
        p[k + 1] = p[k] + R_mid @ d_body
        steps.append(OdometryStep(t[k], t[k + 1], v_cmd, yaw_rate, R_imu.copy(), R_imu_next.copy(), w_true))
        R_imu = R_imu_next
    # rocks near the path, on the ground
    idx = rng.integers(0, K + 1, n_rocks)
    off = rng.uniform(-8.0, 8.0, (n_rocks, 2))
    rocks = p[idx] + np.column_stack([off, rng.normal(-0.3, 0.05, n_rocks)])
    sizes = rng.uniform(0.2, 0.6, n_rocks)
    frames = {}
    for k in range(frame_every - 1, K, frame_every):
        z = (rocks - p[k + 1]) @ R[k + 1]
        r = np.linalg.norm(z, axis=1)
        vis = (r > 1.0) & (r < 8.0) & (z[:, 0] > 0.5) & (np.abs(z[:, 1]) < z[:, 0])
        zv = z[vis]
        cov = stereo_cov(zv)
        noise_z = np.array([rng.multivariate_normal(np.zeros(3), c) for c in cov]).reshape(-1, 3)
        frames[k] = RockObservations(
            t=t[k + 1], xyz_base_m=zv + noise_z, cov_base_m2=cov,
            size_m=sizes[vis] * rng.uniform(0.9, 1.1, vis.sum()), score=np.full(vis.sum(), 0.9))
    return SynthRun(steps, frames, p, R, t, rocks)


def truth_pose(run: SynthRun, k: int) -> GroundTruthPose:
    from scipy.spatial.transform import Rotation

    return GroundTruthPose(run.t[k], run.truth_p[k], Rotation.from_matrix(run.truth_R[k]).as_quat())


def overstate_commands(run: SynthRun, slip: float) -> SynthRun:
    """``run`` with its commanded speeds overstating the driven distance by the share ``slip``
    (the rover drives ``1 - slip`` of what it is commanded)."""
    run.steps = [dataclasses.replace(s, v_mps=s.v_mps / (1.0 - slip)) for s in run.steps]
    return run


def slope_commands(run: SynthRun, slip: float, gain_per_rad: float) -> SynthRun:
    """``run`` with commands overstating the driven distance by ``slip + gain_per_rad * uphill``,
    the uphill pitch (rad, nose up positive) of each step: wheels on loose soil lose more
    uphill and less downhill."""
    from reloc.odometry import uphill_rad

    run.steps = [dataclasses.replace(s, v_mps=s.v_mps / (1.0 - slip - gain_per_rad * uphill_rad(s))) for s in run.steps]
    return run


def wander_commands(run: SynthRun, slip: float, sigma: float, tau_s: float, seed: int) -> SynthRun:
    """``run`` with commands overstating the driven distance by ``slip`` plus a first-order
    Gauss-Markov wander (stationary ``sigma``, correlation time ``tau_s``, seeded): the soil
    under the wheels changing along the way."""
    rng = np.random.default_rng(seed)
    o = sigma * rng.standard_normal()
    steps = []
    for s in run.steps:
        a = np.exp(-s.dt / tau_s)
        o = a * o + sigma * np.sqrt(1.0 - a * a) * rng.standard_normal()
        steps.append(dataclasses.replace(s, v_mps=s.v_mps / (1.0 - slip - o)))
    run.steps = steps
    return run


def drift_heading(run: SynthRun, bias_radps: float) -> SynthRun:
    """``run`` with its IMU heading drifting at ``bias_radps`` about world z (a gyro bias)."""
    t0 = run.t[0]

    def drift(t, R):
        return exp_so3(np.array([0.0, 0.0, bias_radps * (t - t0)])) @ R

    run.steps = [dataclasses.replace(s, R_ref_base0=drift(s.t0, s.R_ref_base0), R_ref_base1=drift(s.t1, s.R_ref_base1))
                 for s in run.steps]
    return run


def end_errors(backend, run: SynthRun, blind_from: int | None = None) -> tuple[float, float, float, float]:
    """Drive any back-end through ``run`` (landmark frames up to step ``blind_from``, then blind)
    and return its final planar error (m) and position NEES, yaw error (rad) and yaw sigma (rad)."""
    from reloc.geometry import wrap_angle, yaw_of

    for k, step in enumerate(run.steps):
        backend.predict(step)
        if (blind_from is None or k < blind_from) and k in run.frames:
            backend.observe(run.frames[k])
    est = backend.estimate()
    e = est.position_m[:2] - run.truth_p[-1, :2]
    yaw_err = float(wrap_angle(yaw_of(est.T_world_base) - yaw_of(run.truth_R[-1])))
    return (float(np.linalg.norm(e)), float(e @ np.linalg.solve(est.cov[:2, :2], e)), yaw_err,
            float(np.sqrt(est.cov[5, 5])))
