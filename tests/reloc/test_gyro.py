"""The gyro monitor: the heading the IMU got wrong between two landmark frames, a bias detected and
corrected only when the landmarks contradict the gyro, the correction's uncertainty carried into
both back-ends' process noise."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reloc.errors import ConfigError
from reloc.geometry import exp_so3, wrap_angle, yaw_of
from reloc.gyro import GyroConfig, GyroMonitor, visual_yaw
from reloc.odometry import OdometryStep

SIGMA = 0.02  # m, per point and axis
UP = np.array([0.0, 0.0, 1.0])


@dataclasses.dataclass
class Frame:
    t: float
    xyz_base_m: np.ndarray
    cov_base_m2: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz_base_m)


def _see(rng, rocks_world, R_wb, p_wb, t, n_clutter=3, drop=0.2, max_range=8.0):
    """Noisy detections of the rocks ahead in base_link (some missed) plus clutter."""
    z = (rocks_world - p_wb) @ R_wb
    keep = (rng.random(len(z)) > drop) & (z[:, 0] > 0.5) & (np.linalg.norm(z, axis=1) < max_range)
    z = z[keep] + rng.normal(0.0, SIGMA, (int(keep.sum()), 3))
    clutter = np.column_stack([rng.uniform(1, 7, n_clutter), rng.uniform(-3, 3, n_clutter), np.zeros(n_clutter)])
    z = np.vstack([z, clutter])
    return Frame(t, z, np.tile(np.eye(3) * SIGMA**2, (len(z), 1, 1)))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), dx=st.floats(0.0, 1.0), yaw=st.floats(-0.3, 0.3),
       delta=st.floats(-0.05, 0.05))
def test_visual_yaw_recovers_the_imu_heading_error_within_its_sigma(seed, dx, yaw, delta):
    rng = np.random.default_rng(seed)
    rocks = np.column_stack([rng.uniform(1.0, 8.0, 30), rng.uniform(-4.0, 4.0, 30), rng.uniform(-0.3, 0.1, 30)])
    R_true = exp_so3(np.array([0.0, 0.0, yaw]))
    d_true = np.array([dx, 0.3 * dx * math.sin(yaw), 0.0])
    a = _see(rng, rocks, np.eye(3), np.zeros(3), 0.0, max_range=20.0)
    b = _see(rng, rocks, R_true, d_true, 8.0, max_range=20.0)
    R_imu = exp_so3(-delta * UP) @ R_true  # the true rotation is the IMU's turned by delta
    vy = visual_yaw(a.xyz_base_m, a.cov_base_m2, b.xyz_base_m, b.cov_base_m2, R_imu, UP, d_true, GyroConfig())
    assert vy is not None and vy.n_inliers >= 10
    assert abs(vy.delta_rad - delta) < 5.0 * vy.sigma_rad
    assert vy.sigma_rad < 0.005
    assert np.linalg.norm(vy.d_m - d_true) < 0.1


def test_visual_yaw_declines_unrelated_frames():
    rng = np.random.default_rng(0)
    mk = lambda: np.column_stack([rng.uniform(1, 8, 25), rng.uniform(-3, 3, 25), np.zeros(25)])
    a = _see(rng, mk(), np.eye(3), np.zeros(3), 0.0, n_clutter=0, drop=0.0)
    b = _see(rng, mk(), np.eye(3), np.zeros(3), 8.0, n_clutter=0, drop=0.0)
    assert visual_yaw(a.xyz_base_m, a.cov_base_m2, b.xyz_base_m, b.cov_base_m2, np.eye(3), UP,
                      np.array([0.5, 0, 0]), GyroConfig()) is None


def _drive(cfg, bias=0.002, window=(30.0, 90.0), t_end=150.0, v=0.08, w=0.01, dt=0.05, seed=2, blind=None):
    """A rover driving a gentle arc at v, yaw rate w; its IMU's heading drifts at ``bias`` rad/s in
    ``window``; frames at 2 Hz. Returns (monitor, corrected steps, true yaw, IMU-integrated yaw
    before and after the correction)."""
    rng = np.random.default_rng(seed)
    rocks = np.column_stack([rng.uniform(-5, 25, 500), rng.uniform(-15, 15, 500), np.zeros(500)])
    mon = GyroMonitor(cfg)
    yaw_true, p = 0.0, np.zeros(3)
    yaw_imu = 0.0
    yaw_corr = 0.0  # heading integrated from the corrected steps
    steps = []
    for k in range(round(t_end / dt)):
        t0, t1 = k * dt, (k + 1) * dt
        b = bias if window[0] <= t0 < window[1] else 0.0
        R0 = exp_so3(np.array([0.0, 0.0, yaw_imu]))
        yaw_imu += (w + b) * dt
        R1 = exp_so3(np.array([0.0, 0.0, yaw_imu]))
        c = mon.correct(OdometryStep(t0, t1, v, w, R0, R1, np.array([0.0, 0.0, w + b])))
        steps.append(c)
        yaw_corr += yaw_of(c.R_ref_base0.T @ c.R_ref_base1)
        p = p + v * dt * np.array([math.cos(yaw_true + 0.5 * w * dt), math.sin(yaw_true + 0.5 * w * dt), 0.0])
        yaw_true += w * dt
        if (k + 1) % 10 == 0 and not (blind and blind[0] <= t1 < blind[1]):
            mon.observe("rocks", _see(rng, rocks, exp_so3(np.array([0.0, 0.0, yaw_true])), p, t1))
    return mon, steps, yaw_true, yaw_imu, yaw_corr


def test_a_bias_step_is_detected_and_the_heading_corrected_then_released():
    mon, steps, yaw_true, yaw_imu, yaw_corr = _drive(GyroConfig())
    assert yaw_imu - yaw_true == pytest.approx(0.12, abs=1e-9)  # 60 s at 0.002 rad/s uncorrected
    # corrected: what the checks needed to confirm it and to see its end (two or three intervals)
    assert abs(wrap_angle(yaw_corr - yaw_true)) < 0.045
    st_ = mon.stats()
    assert st_["n_detections"] == 1 and st_["max_bias_radps"] == pytest.approx(0.002, rel=0.25)
    biased = [c for c in mon.checks if c.biased]
    assert biased and all(30.0 < c.t <= 90.0 + 2 * GyroConfig().baseline_s for c in biased)
    assert not mon.active  # released once the gyro and the landmarks agree again
    widened = [s for s in steps if s.extra_yaw_var_rad2 > 0]
    assert widened and 30.0 < widened[0].t0 < 30.0 + 3.5 * GyroConfig().baseline_s
    # at detection, the heading that went in uncorrected is carried once as variance
    assert widened[0].extra_yaw_var_rad2 > (0.002 * GyroConfig().baseline_s) ** 2
    assert all(s.extra_yaw_var_rad2 < 1e-6 for s in widened[1:])


def test_a_healthy_gyro_is_never_corrected():
    mon, steps, _, yaw_imu, yaw_corr = _drive(GyroConfig(), bias=0.0)
    assert len(mon.checks) >= 15 and mon.stats()["n_biased_checks"] == 0
    assert yaw_corr == pytest.approx(yaw_imu) and all(s.extra_yaw_var_rad2 == 0.0 for s in steps)


def test_a_blind_camera_releases_the_correction_after_hold_s():
    _, steps, *_ = _drive(GyroConfig(hold_s=10.0), window=(30.0, 150.0), blind=(70.0, 150.0))
    widened_t = [s.t0 for s in steps if s.extra_yaw_var_rad2 > 0]
    assert widened_t and max(widened_t) < 70.0 + 10.0 + 0.1


def test_disabled_monitor_changes_nothing():
    mon, _, _, yaw_imu, yaw_corr = _drive(GyroConfig(enabled=False))
    assert yaw_corr == pytest.approx(yaw_imu) and mon.stats()["n_checks"] == 0


def test_config_is_range_checked_by_key():
    from reloc.config import config_from_dict

    with pytest.raises(ConfigError, match="ambiguity_ratio"):
        config_from_dict(GyroConfig, {"ambiguity_ratio": 1.5})
    with pytest.raises(ConfigError, match="baseline_s"):
        GyroConfig(baseline_s=0.0)


def test_extra_heading_variance_reaches_both_back_ends_about_the_gravity_axis_and_splits_in_time():
    from ekf.config import MotionNoiseConfig
    from ekf.motion import propagate, split_step
    from fgslam.smoother.config import OdometryNoiseConfig
    from fgslam.smoother.odometry_factors import step_motion

    R = exp_so3(np.array([0.2, -0.1, 0.7]))  # tilted: the gravity axis is not base_link z
    plain = OdometryStep(0.0, 0.1, 0.2, 0.0, R, R, np.zeros(3))
    wide = dataclasses.replace(plain, extra_yaw_var_rad2=4e-4)
    args = (np.zeros(3), np.eye(3))
    Q0, Q1 = propagate(*args, plain, MotionNoiseConfig())[3], propagate(*args, wide, MotionNoiseConfig())[3]
    assert np.allclose(Q1 - Q0, np.diag([0, 0, 0, 0, 0, 4e-4]))  # world z
    S0, S1 = step_motion(plain, OdometryNoiseConfig())[1], step_motion(wide, OdometryNoiseConfig())[1]
    up = R.T @ UP
    assert np.allclose(S1[:3, :3] - S0[:3, :3], 4e-4 * np.outer(up, up)) and np.allclose(S1[3:], S0[3:])
    a, b = split_step(wide, 0.025)
    assert a.extra_yaw_var_rad2 + b.extra_yaw_var_rad2 == pytest.approx(4e-4)
    assert a.extra_yaw_var_rad2 == pytest.approx(1e-4)


def test_the_ekf_refuses_a_negative_heading_variance():
    from ekf.errors import EkfInputError
    from ekf.slam import EkfSlam
    from reloc.backend import PoseEstimate

    ekf = EkfSlam(PoseEstimate(0.0, np.eye(4), np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])))
    bad = OdometryStep(0.0, 0.1, 0.1, 0.0, np.eye(3), np.eye(3), np.zeros(3), extra_yaw_var_rad2=-1e-6)
    with pytest.raises(EkfInputError, match="extra_yaw_var_rad2"):
        ekf.predict(bad)
