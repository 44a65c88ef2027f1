"""30 Hz IMU: gyro with bias and noise (integrated yaw drifts), gravity-referenced roll/pitch,
accelerometer specific force."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.config import ImuConfig
from sim.sensors.motion import body_rates, ou_process


@dataclass(frozen=True)
class ImuStream:
    """Per tick: ``R_ref_base`` (K, 3, 3) reported orientation (reference = world at the first
    tick, yaw drifting), ``quat_xyzw`` (K, 4), ``gyro_radps`` (K, 3), ``accel_mps2`` (K, 3) in
    base_link, and ``yaw_error_rad`` (K,) the reported minus true yaw."""

    R_ref_base: np.ndarray
    quat_xyzw: np.ndarray
    gyro_radps: np.ndarray
    accel_mps2: np.ndarray
    yaw_error_rad: np.ndarray


def simulate_imu(T_world_base: np.ndarray, dt_s: float, cfg: ImuConfig, rng: np.random.Generator) -> ImuStream:
    """IMU samples for the true poses ``T_world_base`` (K, 4, 4) taken every ``dt_s``."""
    K = len(T_world_base)
    R = T_world_base[:, :3, :3]
    _, w_true = body_rates(T_world_base, dt_s)
    bias = cfg.gyro_bias_sigma_radps * rng.standard_normal(3) + np.cumsum(
        cfg.gyro_bias_walk_radps_rsqrt_s * np.sqrt(dt_s) * rng.standard_normal((K, 3)), axis=0
    )
    white = cfg.gyro_noise_radps_rsqrt_hz / np.sqrt(dt_s) * rng.standard_normal((K, 3))
    gyro = w_true + bias + white
    # first-order yaw error: the gyro error rotated into the world, z part, integrated
    yaw_rate_err = np.einsum("kj,kj->k", R[:, 2, :], bias + white)
    yaw_err = np.concatenate([[0.0], np.cumsum(yaw_rate_err[:-1] * dt_s)])
    tilt = np.column_stack([
        ou_process(K, dt_s, cfg.attitude_noise_rad, 5.0, rng),
        ou_process(K, dt_s, cfg.attitude_noise_rad, 5.0, rng),
        np.zeros(K),
    ])
    R_out = Rotation.from_euler("z", yaw_err[:, None]).as_matrix() @ R @ Rotation.from_rotvec(tilt).as_matrix()
    p = T_world_base[:, :3, 3]
    acc_w = np.zeros_like(p)
    if K >= 3:
        acc_w[1:-1] = (p[2:] - 2 * p[1:-1] + p[:-2]) / dt_s**2
    f_world = acc_w + np.array([0.0, 0.0, cfg.gravity_mps2])
    accel = np.einsum("kji,kj->ki", R, f_world)
    accel += cfg.accel_bias_sigma_mps2 * rng.standard_normal(3)
    accel += cfg.accel_noise_mps2_rsqrt_hz / np.sqrt(dt_s) * rng.standard_normal((K, 3))
    quat = Rotation.from_matrix(R_out).as_quat()
    return ImuStream(R_out, quat, gyro, accel, yaw_err)
