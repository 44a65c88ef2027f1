"""Motion model: command speed along body x, orientation increment from the IMU.

Over a step of ``dt`` with forward speed ``v`` and IMU increment ``dR = R_ref_base0^T R_ref_base1``:

    R1 = R0 dR
    p1 = p0 + R_mid [v dt, 0, 0]^T,    R_mid = R0 Exp(Log(dR) / 2)

Error state ``[dp_world, dtheta_world]`` with ``R_true = Exp(dtheta) R``: the Jacobian is
``F = [[I, -[R_mid d]x], [0, I]]`` (``d = [v dt, 0, 0]``). Process noise enters as body-frame
translation noise rotated by ``R_mid`` and body-frame rotation noise rotated by ``R1``; its
variances follow :class:`ekf.config.MotionNoiseConfig`. A step's ``extra_yaw_var_rad2`` (the gyro
monitor's, :mod:`reloc.gyro`) adds to the heading's variance about world z.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ekf.config import MotionNoiseConfig
from reloc.geometry import exp_so3, log_so3, skew
from reloc.odometry import OdometryStep, pitch_rad


def body_rates(step: OdometryStep) -> np.ndarray:
    """Mean body angular rate (3,) rad/s over the step, from the IMU orientation increment."""
    return log_so3(step.R_ref_base0.T @ step.R_ref_base1) / step.dt


def process_noise_body(
    step: OdometryStep, cfg: MotionNoiseConfig, w: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Variances (3,), (3,) of body-frame translation (m^2) and rotation (rad^2) noise over the
    step; ``w`` (3,) rad/s the body rates if already known."""
    w = body_rates(step) if w is None else w
    speed = abs(step.v_mps)
    turn = abs(float(w[2]))
    rough = math.hypot(float(w[0]), float(w[1]))
    extra = cfg.trans_per_rough * speed * rough
    s_fwd = cfg.fwd_floor + cfg.fwd_per_speed * speed + extra
    s_lat = cfg.lat_floor + cfg.lat_per_speed * speed + cfg.lat_per_turn * turn + extra
    s_vert = cfg.vert_floor + cfg.vert_per_speed * speed + extra
    s_rot = cfg.rot_floor + cfg.rot_per_turn * turn + cfg.rot_per_rough * rough
    dist = speed * step.dt
    fwd_slip2 = cfg.fwd_per_sqrtm**2 + (cfg.fwd_per_sqrtm_per_rad * pitch_rad(step)) ** 2
    var_t = np.array([s_fwd, s_lat, s_vert]) ** 2 * step.dt + dist * np.array([fwd_slip2, cfg.lat_per_sqrtm**2, 0.0])
    var_t[0] += step.extra_forward_var_m2
    var_r = np.full(3, s_rot**2 * step.dt)
    return var_t, var_r


def propagate(
    p_world: np.ndarray, R_world_base: np.ndarray, step: OdometryStep, cfg: MotionNoiseConfig,
    p_lin: np.ndarray | None = None, yaw_bias_radps: float = 0.0, slip: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One prediction: returns ``p1`` (3,), ``R1`` (3, 3), the error-state Jacobian ``F`` (6, 6)
    and the process noise ``Q`` (6, 6), both over ``[dp_world, dtheta_world]``.

    ``p_lin``: the position the previous prediction reached (first-estimate Jacobians): ``F``'s
    rotation-to-position block is then ``-[p1 - p_lin]x`` instead of ``-[p1 - p_world]x``, so a
    yaw of the whole world about z stays an unobservable direction across the updates made in
    between (Huang, Mourikis and Roumeliotis, "A First-Estimates Jacobian EKF for improving SLAM
    consistency", 2008). ``yaw_bias_radps``: the IMU heading's drift rate about world z, taken
    out of the increment (``R1 = Exp(-b dt e_z) R0 dR``; its Jacobian is the filter's, see
    :meth:`ekf.state.FilterState.yaw_bias_step`). ``slip``: the share of the commanded distance
    not driven on this step's slope (``d = (1 - slip) v dt``, :meth:`ekf.state.FilterState.slip_at`;
    its Jacobian: :meth:`ekf.state.FilterState.slip_step`)."""
    dR = step.R_ref_base0.T @ step.R_ref_base1
    rotvec = log_so3(dR)
    R0 = R_world_base
    if yaw_bias_radps:  # half the step's drift taken out before the mid rotation, half after
        half = exp_so3(np.array([0.0, 0.0, -0.5 * yaw_bias_radps * step.dt]))
        R0 = half @ R_world_base
        R_mid = R0 @ exp_so3(0.5 * rotvec)
        R1 = half @ R0 @ dR
    else:
        R_mid = R0 @ exp_so3(0.5 * rotvec)
        R1 = R0 @ dR
    d_world = R_mid[:, 0] * ((1.0 - slip) * step.v_mps * step.dt)  # slip: at this step's slope
    p1 = p_world + d_world
    F = np.eye(6)
    F[:3, 3:] = -skew(d_world if p_lin is None else p1 - p_lin)
    var_t, var_r = process_noise_body(step, cfg, rotvec / step.dt)
    Q = np.zeros((6, 6))
    Q[:3, :3] = (R_mid * var_t) @ R_mid.T
    Q[3:, 3:] = (R1 * var_r) @ R1.T
    Q[5, 5] += step.extra_yaw_var_rad2
    return p1, R1, F, Q


def split_step(step: OdometryStep, t: float) -> tuple[OdometryStep, OdometryStep]:
    """Split a step at ``t0 < t < t1``: same speed, the IMU orientation interpolated on SO(3), the
    extra forward and heading variances shared in proportion to time."""
    a = (t - step.t0) / step.dt
    dR = step.R_ref_base0.T @ step.R_ref_base1
    R_t = step.R_ref_base0 @ exp_so3(a * log_so3(dR))
    f, y = step.extra_forward_var_m2, step.extra_yaw_var_rad2
    return (dataclasses.replace(step, t1=t, R_ref_base1=R_t, extra_forward_var_m2=a * f, extra_yaw_var_rad2=a * y),
            dataclasses.replace(step, t0=t, R_ref_base0=R_t, extra_forward_var_m2=(1.0 - a) * f,
                                extra_yaw_var_rad2=(1.0 - a) * y))
