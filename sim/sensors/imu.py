"""30 Hz IMU: gyro with bias and noise (integrated yaw drifts), gravity-referenced roll/pitch,
accelerometer specific force."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.config import ImuConfig
from sim.sensors.motion import OUProcess, body_rates


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


class ImuModel:
    """The IMU of :func:`simulate_imu`, chunk after chunk: :meth:`step` continues the gyro bias
    walk, the integrated yaw error and the attitude noise where the last chunk ended (a whole run
    in one chunk is :func:`simulate_imu`, draw for draw)."""

    def __init__(self, cfg: ImuConfig, dt_s: float, rng: np.random.Generator) -> None:
        self.cfg, self.dt_s, self.rng = cfg, dt_s, rng
        self._tilt = [OUProcess(dt_s, cfg.attitude_noise_rad, 5.0, rng) for _ in range(2)]
        self._bias: np.ndarray | None = None  # gyro bias at the last tick
        self._accel_bias: np.ndarray | None = None
        self._yaw_err = 0.0  # integrated yaw error at the first tick of the next chunk

    def step(self, T_world_base: np.ndarray, T_prev: np.ndarray | None = None,
             T_next: np.ndarray | None = None) -> ImuStream:
        """Samples for the true poses ``T_world_base`` (K, 4, 4); ``T_prev`` / ``T_next`` (4, 4):
        the poses just before and after the chunk (None at the run's ends)."""
        cfg, dt_s, rng = self.cfg, self.dt_s, self.rng
        K = len(T_world_base)
        R = T_world_base[:, :3, :3]
        _, w_true = body_rates(T_world_base, dt_s, T_next)
        if self._bias is None:
            self._bias = cfg.gyro_bias_sigma_radps * rng.standard_normal(3)
        bias = self._bias + np.cumsum(cfg.gyro_bias_walk_radps_rsqrt_s * np.sqrt(dt_s) * rng.standard_normal((K, 3)), axis=0)
        self._bias = bias[-1]
        white = cfg.gyro_noise_radps_rsqrt_hz / np.sqrt(dt_s) * rng.standard_normal((K, 3))
        gyro = w_true + bias + white
        # first-order yaw error: the gyro error rotated into the world, z part, integrated
        yaw_rate_err = np.einsum("kj,kj->k", R[:, 2, :], bias + white)
        yaw_err = np.concatenate([[0.0], np.cumsum(yaw_rate_err[:-1] * dt_s)])
        if self._yaw_err:
            yaw_err = yaw_err + self._yaw_err
        self._yaw_err = float(yaw_err[-1] + yaw_rate_err[-1] * dt_s)
        tilt = np.column_stack([self._tilt[0].sample(K), self._tilt[1].sample(K), np.zeros(K)])
        R_out = Rotation.from_euler("z", yaw_err[:, None]).as_matrix() @ R @ Rotation.from_rotvec(tilt).as_matrix()
        p = T_world_base[:, :3, 3]
        ext = [p] if T_prev is None else [T_prev[None, :3, 3], p]
        if T_next is not None:
            ext.append(T_next[None, :3, 3])
        q = np.concatenate(ext) if len(ext) > 1 else p
        acc_q = np.zeros_like(q)
        if len(q) >= 3:
            acc_q[1:-1] = (q[2:] - 2 * q[1:-1] + q[:-2]) / dt_s**2
        acc_w = acc_q[(T_prev is not None):][:K]
        f_world = acc_w + np.array([0.0, 0.0, cfg.gravity_mps2])
        accel = np.einsum("kji,kj->ki", R, f_world)
        if self._accel_bias is None:
            self._accel_bias = cfg.accel_bias_sigma_mps2 * rng.standard_normal(3)
        accel += self._accel_bias
        accel += cfg.accel_noise_mps2_rsqrt_hz / np.sqrt(dt_s) * rng.standard_normal((K, 3))
        quat = Rotation.from_matrix(R_out).as_quat()
        return ImuStream(R_out, quat, gyro, accel, yaw_err)


def simulate_imu(T_world_base: np.ndarray, dt_s: float, cfg: ImuConfig, rng: np.random.Generator) -> ImuStream:
    """IMU samples for the true poses ``T_world_base`` (K, 4, 4) taken every ``dt_s``."""
    return ImuModel(cfg, dt_s, rng).step(T_world_base)
