"""Odometry between keyframes: accumulate OdometryStep motion with propagated covariance, and
turn it into GTSAM between-factors and gravity (roll/pitch) factors.

The motion of one step is a rotation from the IMU orientation increment and a translation of
``v * dt`` along base_link x (taken at the mid rotation). Covariances are in GTSAM's body-frame
[rot, trans] tangent at the end of the accumulated motion:
``cov' = Ad(dT^-1) cov Ad(dT^-1)^T + Q_step``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from fgslam.smoother.config import OdometryNoiseConfig
from reloc.geometry import skew
from reloc.odometry import OdometryStep, pitch_rad, step_translation


def step_motion(step: OdometryStep, cfg: OdometryNoiseConfig) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4) base-frame motion ``T_base0_base1`` of one step and its (6, 6) noise covariance.

    The translation runs along the chord of the step's arc (:func:`reloc.odometry.step_translation`)."""
    dR = step.dR_base
    d_m = step.v_mps * step.dt
    dT = np.eye(4)
    dT[:3, :3] = dR
    dT[:3, 3] = step_translation(step, dR)
    ad = abs(d_m)
    slope = pitch_rad(step)
    s_f2 = (cfg.sigma_forward_m_per_sqrtm**2 + (cfg.sigma_forward_m_per_sqrtm_per_rad * slope) ** 2) * ad
    s_f2 += cfg.floor_sigma_m**2 + step.extra_forward_var_m2
    s_l2 = cfg.sigma_lateral_m_per_sqrtm**2 * ad + cfg.floor_sigma_m**2
    s_r2 = cfg.sigma_rot_radpsqrts**2 * max(step.dt, 0.0) + cfg.floor_sigma_rad**2
    Q = np.diag([s_r2, s_r2, s_r2, s_f2, s_l2, s_l2])
    return dT, Q



def adjoint_inverse(T: np.ndarray) -> np.ndarray:
    """(6, 6) adjoint of ``T^-1`` in GTSAM's [rot, trans] ordering, without forming the inverse."""
    Rt = T[:3, :3].T
    t = T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = Rt
    Ad[3:, 3:] = Rt
    Ad[3:, :3] = -Rt @ skew(t)
    return Ad


class OdometryAccumulator:
    """Motion since the last keyframe, ``T_kf_now`` (4, 4) with covariance ``cov`` (6, 6, GTSAM
    body frame at now), plus a per-step history so that a late fix can be placed at any time."""

    def __init__(self, t_kf: float) -> None:
        self.t_kf = t_kf
        self.T_kf_now = np.eye(4)
        self.cov = np.zeros((6, 6))
        self.distance_m = 0.0
        self.t_now = t_kf
        self.R_ref_base: np.ndarray | None = None  # latest IMU orientation (gravity reference)
        self.history_t: list[float] = [t_kf]
        self.history_T: list[np.ndarray] = [np.eye(4)]
        self.history_cov: list[np.ndarray] = [np.zeros((6, 6))]

    def push(self, step: OdometryStep, cfg: OdometryNoiseConfig) -> None:
        """Compose one odometry step onto the accumulated motion."""
        dT, Q = step_motion(step, cfg)
        Ad = adjoint_inverse(dT)
        self.T_kf_now = self.T_kf_now @ dT
        self.cov = Ad @ self.cov @ Ad.T + Q
        self.distance_m += abs(step.v_mps * step.dt)
        self.t_now = step.t1
        self.R_ref_base = step.R_ref_base1
        self.history_t.append(step.t1)
        self.history_T.append(self.T_kf_now.copy())
        self.history_cov.append(self.cov.copy())

    def yaw_change_rad(self) -> float:
        """Absolute heading change since the keyframe (rad)."""
        R = self.T_kf_now[:3, :3]
        return float(abs(np.arctan2(R[1, 0], R[0, 0])))

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Accumulated motion (4, 4) and covariance (6, 6) at the latest step not after ``t``."""
        i = int(np.searchsorted(self.history_t, t, side="right")) - 1
        i = max(i, 0)
        return self.history_T[i], self.history_cov[i]


def between_factor(k0: int, k1: int, T_kf0_kf1: np.ndarray, cov: np.ndarray) -> gtsam.BetweenFactorPose3:
    """Between-factor X(k0) -> X(k1) with measured motion (4, 4) and covariance (6, 6, [rot, trans])."""
    C = 0.5 * (cov + cov.T)
    return gtsam.BetweenFactorPose3(k0, k1, gtsam.Pose3(T_kf0_kf1), gtsam.noiseModel.Gaussian.Covariance(C))


def gravity_factor(key: int, R_ref_base: np.ndarray, sigma_rad: float) -> gtsam.AttitudeFactorPose3:
    """Roll/pitch factor on X(key): the IMU's gravity-referenced z axis seen in base_link
    (``R_ref_base.T @ e_z``) must map to the world z axis. Yaw stays free."""
    b_z = np.asarray(R_ref_base).T @ np.array([0.0, 0.0, 1.0])
    model = gtsam.noiseModel.Isotropic.Sigma(2, sigma_rad)
    return gtsam.AttitudeFactorPose3(key, gtsam.Unit3(np.array([0.0, 0.0, 1.0])), model, gtsam.Unit3(b_z))
