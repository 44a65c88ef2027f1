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
    if step.extra_yaw_var_rad2:  # the gyro monitor's heading variance, about the gravity axis (reloc.gyro)
        up = np.asarray(step.R_ref_base1)[2, :]  # R^T e_z: world z in base_link at the step's end
        Q[:3, :3] += step.extra_yaw_var_rad2 * np.outer(up, up)
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


def slipped_motion(T_kf0_kf1: np.ndarray, g: float) -> np.ndarray:
    """(4, 4): the accumulated odometry motion with its translation scaled by ``1 - g`` (the share
    ``g`` of the commanded distance lost to slip; every step's translation scales alike)."""
    T = np.array(T_kf0_kf1, dtype=float)
    T[:3, 3] *= 1.0 - g
    return T


def corrected_motion(T_kf0_kf1: np.ndarray, g: float, yaw_drift_rad: float, R_world_kf0: np.ndarray) -> np.ndarray:
    """(4, 4): the accumulated motion with its translation scaled by ``1 - g`` and the IMU heading's
    drift over it (``yaw_drift_rad``, about world z) taken out of its rotation,
    ``Exp(-drift R0^T e_z) dR`` (the EKF's ``R1 = Exp(-b dt e_z) R0 dR``, :mod:`ekf.motion`)."""
    T = slipped_motion(T_kf0_kf1, g)
    if yaw_drift_rad:
        u = np.asarray(R_world_kf0)[2, :]  # world z in the keyframe's body frame
        T[:3, :3] = gtsam.Rot3.Expmap(-yaw_drift_rad * u).matrix() @ T[:3, :3]
    return T


def odometry_residual(X0: gtsam.Pose3, X1: gtsam.Pose3, g: float, b: float, dt_s: float, T_kf0_kf1: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residual (6,) ``Log(M^-1 X0^-1 X1)`` of the between-factor (GTSAM's BetweenFactor
    convention) whose measured motion ``M`` is the odometry corrected by the slip ``g`` and the
    yaw-rate bias ``b`` (rad/s) over ``dt_s`` (:func:`corrected_motion`), and its Jacobians w.r.t.
    X0, X1 (6, 6), g (6, 1) and b (6, 1). In M's tangent, ``dM/dg = [0, -R_M^T t]`` (t the
    unscaled translation) and ``dM/db = [-dt R_M^T u, 0]`` (u = world z in X0's frame; u's own
    dependence on X0's attitude, a term of order b dt, is left out)."""
    R0 = X0.rotation().matrix()
    T = corrected_motion(T_kf0_kf1, g, b * dt_s, R0)
    M = gtsam.Pose3(T)
    H0, H1 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    B = X0.between(X1, H0, H1)
    HM, HB = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    E = M.between(B, HM, HB)
    HE = np.zeros((6, 6), order="F")
    e = gtsam.Pose3.Logmap(E, HE)
    RmT = T[:3, :3].T
    dg, db = np.zeros(6), np.zeros(6)
    dg[3:] = -RmT @ np.asarray(T_kf0_kf1)[:3, 3]
    db[:3] = -dt_s * RmT @ R0[2, :]
    HEB, HEM = HE @ HB, HE @ HM
    return (np.asarray(e, dtype=float).ravel(), HEB @ H0, HEB @ H1, (HEM @ dg)[:, None], (HEM @ db)[:, None])


def odometry_factor(k0: int, k1: int, T_kf0_kf1: np.ndarray, cov: np.ndarray, dt_s: float,
                    slip_key: int | None = None, bias_key: int | None = None) -> gtsam.NonlinearFactor:
    """Between-factor X(k0) -> X(k1) of the accumulated odometry (4, 4) with covariance (6, 6,
    [rot, trans]); with a slip variable ``slip_key`` and / or a yaw-rate bias variable
    ``bias_key`` (doubles) the measured motion is corrected by them (:func:`odometry_residual`, a
    CustomFactor, one per keyframe), else GTSAM's C++ BetweenFactorPose3."""
    if slip_key is None and bias_key is None:
        return between_factor(k0, k1, T_kf0_kf1, cov)
    T = np.array(T_kf0_kf1, dtype=float)
    model = gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))
    keys = [k0, k1] + [k for k in (slip_key, bias_key) if k is not None]
    i_g = 2 if slip_key is not None else None
    i_b = (3 if slip_key is not None else 2) if bias_key is not None else None

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        k = this.keys()
        g = values.atDouble(k[i_g]) if i_g is not None else 0.0
        b = values.atDouble(k[i_b]) if i_b is not None else 0.0
        r, A0, A1, Ag, Ab = odometry_residual(values.atPose3(k[0]), values.atPose3(k[1]), g, b, dt_s, T)
        if H is not None:
            H[0], H[1] = A0, A1
            if i_g is not None:
                H[i_g] = Ag
            if i_b is not None:
                H[i_b] = Ab
        return r

    return gtsam.CustomFactor(model, keys, error)


def random_walk_factor(key0: int, key1: int, dt_s: float, walk_rsqrt_s: float) -> gtsam.BetweenFactorDouble:
    """Random walk of a scalar variable (slip, yaw-rate bias) between two keyframes ``dt_s``
    apart, ``walk_rsqrt_s`` per sqrt(s) (C++)."""
    sigma = max(walk_rsqrt_s * np.sqrt(max(dt_s, 0.0)), 1e-9)
    return gtsam.BetweenFactorDouble(key0, key1, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, sigma))
