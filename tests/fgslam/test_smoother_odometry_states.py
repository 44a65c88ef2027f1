"""The wheels' slip and the IMU's yaw-rate bias as smoother variables. Slip: commands that overstate the driven distance by a
constant share are learned from the landmarks' motion over 50 s, and through the 40 s without
landmarks that follow the smoother carries the rover on the corrected speed, inside its sigma; the
white slip terms alone end farther off. Bias: the landmarks' relative rotations observe it, the
smoother learns it within its sigma and keeps its heading honest; without the variable the same
drift leaves the heading outside 3 sigma. The odometry factor's Jacobians match numerical
differences."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from ekf.config import MotionNoiseConfig
from fgslam.smoother import Isam2Smoother, SmootherConfig
from fgslam.smoother.config import OdometryNoiseConfig
from fgslam.smoother.odometry_factors import odometry_residual
from reloc.backend import PoseEstimate
from reloc.geometry import exp_so3, log_so3
from tests.ekf.ekf_synth import drift_heading, end_errors, overstate_commands, simulate

SLIP = 0.06  # the rover drives 94 % of what it is commanded
SIGMA = 0.05  # the variable's prior (OdometryNoiseConfig.slip_sigma)
BLIND_FROM = 50 * 30  # step index (30 Hz): landmarks for 50 s, then 40 s blind
QUIET = MotionNoiseConfig(fwd_per_sqrtm=0.01, fwd_per_speed=0.005)
START = PoseEstimate(0.0, np.eye(4), np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]))


@pytest.fixture(scope="module")
def slipping():
    # a quiet world (forward white noise 0.01 m/sqrt(m)): the constant share is then the slip
    return overstate_commands(simulate(4, duration_s=90.0, frame_every=6, n_rocks=250, noise=QUIET), SLIP)


def R_mid(run, k):
    """The true rotation halfway through step ``k``."""
    R0, R1 = run.truth_R[k], run.truth_R[k + 1]
    return R0 @ exp_so3(0.5 * log_so3(R0.T @ R1))


def _drive(run, slip_sigma):
    # the white terms of the test world (ekf_synth draws them as the EKF's process noise)
    cfg = SmootherConfig(odometry=OdometryNoiseConfig(sigma_forward_m_per_sqrtm=0.012, sigma_lateral_m_per_sqrtm=0.015,
                                                      slip_sigma=slip_sigma))
    sm = Isam2Smoother(START, cfg)
    err, nees, *_ = end_errors(sm, run, BLIND_FROM)  # then blind: the wheels alone carry the rover
    return sm, err, nees


def test_the_smoother_learns_the_slip_and_drives_blind_on_it(slipping):
    sm, err, nees = _drive(slipping, SIGMA)
    rep = sm.stats().extra["slip"]
    # the slip the rover had while it saw landmarks: the share of its commanded distance that its
    # true along-track motion lacks (the world's white slip on slopes adds to SLIP)
    along = [(R_mid(slipping, k).T @ (slipping.truth_p[k + 1] - slipping.truth_p[k]))[0] for k in range(BLIND_FROM)]
    realized = 1.0 - sum(along) / sum(s.v_mps * s.dt for s in slipping.steps[:BLIND_FROM])
    assert abs(rep["estimate"] - realized) <= 3 * rep["sigma"] and rep["sigma"] < 0.5 * SIGMA  # learned
    assert nees <= 11.8  # chi2(2 dof) 99.7 %
    sm_white, err_white, _ = _drive(slipping, 0.0)
    assert "slip" not in sm_white.stats().extra
    assert err < 0.65 * err_white


BIAS = 1.5e-3  # rad/s: 5 deg in 60 s, so that one test minute shows it


@pytest.fixture(scope="module")
def drifting():
    return drift_heading(simulate(3, duration_s=60.0, frame_every=6, n_rocks=250), BIAS)


def _drive_heading(run, bias_sigma):
    cfg = SmootherConfig(odometry=OdometryNoiseConfig(sigma_rot_radpsqrts=2e-4, yaw_rate_bias_sigma_radps=bias_sigma))
    sm = Isam2Smoother(START, cfg)
    *_, err, sig = end_errors(sm, run)
    return sm, err, sig


def test_the_smoother_learns_the_yaw_rate_bias_and_keeps_its_heading(drifting):
    sigma_b = 3e-3
    sm, err, sig = _drive_heading(drifting, sigma_b)
    rep = sm.stats().extra["yaw_rate_bias_deg_per_h"]
    per_h = np.degrees(1.0) * 3600.0
    assert abs(rep["estimate"] - BIAS * per_h) <= 3 * rep["sigma"] and rep["sigma"] < 0.5 * sigma_b * per_h
    assert abs(err) <= 3 * sig


def test_without_the_bias_variable_the_heading_is_overconfident(drifting):
    sm, err, sig = _drive_heading(drifting, 0.0)
    assert "yaw_rate_bias_deg_per_h" not in sm.stats().extra
    assert abs(err) > 3 * sig


def test_odometry_factor_jacobians_match_numerical_differences():
    rng = np.random.default_rng(1)
    X0 = gtsam.Pose3.Expmap(rng.normal(size=6))
    T = gtsam.Pose3.Expmap(np.r_[0.02, -0.01, 0.1, 0.5, 0.02, 0.01]).matrix()
    X1 = X0.compose(gtsam.Pose3(T)).compose(gtsam.Pose3.Expmap(0.05 * rng.normal(size=6)))
    g, b, dt, eps = 0.03, 2e-3, 1.5, 1e-6

    def res(X0_, X1_, g_, b_):
        return odometry_residual(X0_, X1_, g_, b_, dt, T)

    e, A0, A1, Ag, Ab = res(X0, X1, g, b)
    num0 = np.column_stack([(res(X0.retract(eps * d), X1, g, b)[0] - e) / eps for d in np.eye(6)])
    num1 = np.column_stack([(res(X0, X1.retract(eps * d), g, b)[0] - e) / eps for d in np.eye(6)])
    np.testing.assert_allclose(A0, num0, atol=5 * b * dt)  # less the bias term's attitude dependence
    np.testing.assert_allclose(A1, num1, atol=1e-6)
    np.testing.assert_allclose(Ag[:, 0], (res(X0, X1, g + eps, b)[0] - e) / eps, atol=1e-6)
    np.testing.assert_allclose(Ab[:, 0], (res(X0, X1, g, b + eps)[0] - e) / eps, atol=1e-6)
    # at the measured motion with the slip applied (and no bias), the residual vanishes
    Xs = X0.compose(gtsam.Pose3(gtsam.Rot3(T[:3, :3]), (1 - g) * T[:3, 3]))
    assert np.abs(res(X0, Xs, g, 0.0)[0]).max() < 1e-9
