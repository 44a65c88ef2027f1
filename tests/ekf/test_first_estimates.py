"""First-estimate Jacobians: landmarks alone carry no information on the global position and yaw
(SLAM's unobservable directions), nor on the stereo range scale, so the filter's covariance
along them never falls below the start's (the scale's prior). With Jacobians at the current estimate the linearised filter observes a yaw it cannot
see (Huang, Mourikis and Roumeliotis 2008): the test below fails that way."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ekf_synth import simulate

from ekf.config import EkfConfig
from ekf.slam import EkfSlam
from reloc.backend import PoseEstimate

SIGMA_P0, SIGMA_YAW0 = 0.5, np.radians(3.0)  # a start known this well: no landmark can do better


@pytest.fixture(scope="module")
def run():
    return simulate(5, duration_s=60.0, frame_every=6, n_rocks=250)


def _start() -> PoseEstimate:
    return PoseEstimate(0.0, np.eye(4), np.diag([SIGMA_P0**2, SIGMA_P0**2, SIGMA_P0**2, 1e-6, 1e-6, SIGMA_YAW0**2]))


def _drive(run, cfg: EkfConfig) -> EkfSlam:
    ekf = EkfSlam(_start(), cfg)
    for k, step in enumerate(run.steps):
        ekf.predict(step)
        if k in run.frames:
            ekf.observe(run.frames[k])
    return ekf


def _unobservable_info(ekf: EkfSlam) -> np.ndarray:
    """Information (4, 4) of the whole state along a common translation (x, y, z) and a yaw of
    the whole world about z, each direction scaled to its start sigma (1 at the start)."""
    s = ekf._s
    n = s.P.shape[0]
    p, l = s.jacobian_points()  # the first estimates, or the current estimate without them
    N = np.zeros((n, 4))
    for i in range(3):  # translation: pose and every landmark move together
        N[i, i] = SIGMA_P0
        N[s.head + i::3, i] = SIGMA_P0
    ez = np.array([0.0, 0.0, 1.0])
    N[:3, 3] = np.cross(ez, p) * SIGMA_YAW0
    N[3:6, 3] = ez * SIGMA_YAW0
    N[s.head:, 3] = (np.cross(ez, l) * SIGMA_YAW0).reshape(-1)
    return N.T @ np.linalg.solve(s.P, N)


def test_landmarks_alone_do_not_observe_global_yaw_or_position(run):
    ekf = _drive(run, EkfConfig())
    assert ekf._s.n_landmarks > 20
    info = _unobservable_info(ekf)
    # the start's information along these directions, and no more (process noise only lowers it)
    assert np.all(np.linalg.eigvalsh(info) <= 1.0 + 1e-6), np.linalg.eigvalsh(info)
    yaw_sigma = np.sqrt(ekf.estimate().cov[5, 5])
    assert yaw_sigma >= SIGMA_YAW0 * (1 - 1e-6)


def test_jacobians_at_the_current_estimate_gain_spurious_yaw_information(run):
    """The same drive linearised at the current estimate: the filter believes it knows the yaw
    better than it started (why first estimates are the default)."""
    ekf = _drive(run, dataclasses.replace(EkfConfig(), first_estimate_jacobians=False))
    info = _unobservable_info(ekf)
    assert np.linalg.eigvalsh(info).max() > 1.05


def _scale_sigma_without_wheels(run, fej: bool) -> float:
    """The range scale's sigma after the drive, the wheels' distance made worthless: only the
    landmarks could inform the scale, and they cannot (scaling map and path leaves them as they are)."""
    from reloc.calibration import CalibrationConfig

    motion = dataclasses.replace(EkfConfig().motion, fwd_per_sqrtm=3.0, fwd_per_speed=3.0)
    cfg = dataclasses.replace(EkfConfig(), motion=motion, first_estimate_jacobians=fej, slip_sigma=0.0,
                              calibration=CalibrationConfig(scale_sigma=0.01))
    ekf = _drive(run, cfg)
    return float(ekf.calibration()["scale_sigma"])


def test_landmarks_alone_do_not_observe_the_range_scale(run):
    assert _scale_sigma_without_wheels(run, True) >= 0.01 * 0.98
    assert _scale_sigma_without_wheels(run, False) < 0.01 * 0.9  # the moving estimate "learns" it


def test_uninformative_fixes_give_no_yaw_information(run):
    """Fixes carrying (almost) no information leave the unobservable directions as landmarks
    alone leave them: a fix no longer re-linearises every landmark at the current estimate (each
    such reset handed the filter yaw information it did not have; with a fix every 10 s on
    rocky-1km, fixes of 10^4 m sigma took the EKF from 0.26 to 0.70 m ATE in 900 s)."""
    from reloc.geometry import yaw_of
    from reloc.measurements import GlobalFix

    ekf = EkfSlam(_start(), EkfConfig())
    n_fixes = n_frames = 0
    for k, step in enumerate(run.steps):
        ekf.predict(step)
        if k in run.frames:
            ekf.observe(run.frames[k])
            n_frames += 1
            if n_frames % 30 == 0:
                est = ekf.estimate()
                p = est.T_world_base[:3, 3]
                fix = GlobalFix(est.t, est.t, p[0], p[1], float(yaw_of(est.T_world_base)), np.eye(3) * 1e8)
                n_fixes += ekf.apply_fix(fix).accepted
    assert n_fixes >= 5
    assert np.all(np.linalg.eigvalsh(_unobservable_info(ekf)) <= 1.0 + 1e-6)
