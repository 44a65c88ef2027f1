"""Crater measurements in both back-ends against numerical derivatives: the iSAM2 factor the
crater layer builds for a partial rim, and the EKF crater update against a Kalman update built
from central differences of ``h = R^T (l - p)``."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from ekf.config import EkfConfig
from ekf.craters import CraterUpdate
from fgslam.backends.registry import make_backend
from fgslam.smoother.config import SmootherConfig
from fgslam.smoother.craters import CraterLandmarks
from fgslam.smoother.factors import point_factor_covariance
from reloc.backend import PoseEstimate
from reloc.craters import CraterObservations, rim_fit_covariance
from reloc.geometry import exp_so3
from reloc.kinds import kind_named


def _partial_rim_cov(z: np.ndarray) -> np.ndarray:
    """A rim centre covariance (3, 3) in base_link for a 60-degree arc seen on the line to ``z``."""
    a = np.deg2rad(np.linspace(150, 210, 25))  # the near arc, facing the rover
    C = rim_fit_covariance(a, 0.3)
    yaw = np.arctan2(z[1], z[0])
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    out = np.zeros((3, 3))
    out[:2, :2], out[2, 2] = C[:2, :2], 0.05
    return R @ out @ R.T


def _num_pose(f, T: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    P = gtsam.Pose3(T)
    return np.column_stack([(f(P.retract(d).matrix()) - f(P.retract(-d).matrix())) / (2 * eps) for d in np.eye(6) * eps])


@pytest.mark.parametrize("seed", range(4))
def test_the_crater_factor_jacobians_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    T = gtsam.Pose3(gtsam.Rot3.Ypr(rng.uniform(-3, 3), rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)),
                    rng.normal(0, 50, 3)).matrix()
    z = np.array([rng.uniform(8, 25), rng.uniform(-8, 8), rng.uniform(-1, 0.5)])
    cov = _partial_rim_cov(z)
    layer = CraterLandmarks(SmootherConfig(), kind_named("craters"), None)
    f = layer._point_factor(0, 0, z, cov)
    assert isinstance(f, gtsam.BearingRangeFactor3D)  # C++, not a Python CustomFactor
    l_world = T[:3, :3] @ z + T[:3, 3]
    xk, rk = gtsam.symbol("x", 0), layer.key(0)

    def err(Tp, lp=l_world):
        v = gtsam.Values()
        v.insert(xk, gtsam.Pose3(Tp))
        v.insert(rk, lp)
        return f.unwhitenedError(v)

    v = gtsam.Values()
    v.insert(xk, gtsam.Pose3(T))
    v.insert(rk, l_world)
    A, _ = f.linearize(v).jacobian()
    W = np.linalg.cholesky(np.linalg.inv(point_factor_covariance(z, cov * layer.cfg.rock_cov_scale))).T
    Hp = _num_pose(err, T)
    Hl = np.column_stack([(err(T, l_world + e) - err(T, l_world - e)) / 2e-6 for e in np.eye(3) * 1e-6])
    np.testing.assert_allclose(A, W @ np.hstack([Hp, Hl]), rtol=1e-5, atol=1e-5)
    # the partial rim's long axis stays long: a shift along the line of sight costs less than across
    u = z / np.linalg.norm(z)
    side = np.cross([0, 0, 1.0], u)
    side /= np.linalg.norm(side)
    e_along = np.linalg.norm(A[:, 6:] @ (T[:3, :3] @ u) * 0.5)
    e_across = np.linalg.norm(A[:, 6:] @ (T[:3, :3] @ side) * 0.5)
    assert e_across > 2.5 * e_along


def _perturb(x: np.ndarray, d: np.ndarray):
    p, R, l = x
    return p + d[:3], exp_so3(d[3:6]) @ R, l + d[6:9]


def _h(x) -> np.ndarray:
    p, R, l = x
    return R.T @ (l - p)


def test_the_ekf_crater_update_is_the_kalman_update_of_numerical_jacobians():
    """One crater landmark in the state; a second frame's rim centre updates pose and landmark by
    exactly K (z - h) with H from central differences (Joseph form, same prior)."""
    T0 = np.eye(4)
    T0[:3, :3] = exp_so3(np.array([0.02, -0.01, 0.4]))
    T0[:3, 3] = [10.0, -4.0, 1.0]
    est = PoseEstimate(0.0, T0, np.diag([0.3, 0.3, 0.05, 1e-3, 1e-3, 4e-3]))
    # the pose and the landmark only (no yaw-rate bias, slip or fix offset states: the measurement does not see them)
    be = make_backend("ekf", est, {"yaw_rate_bias_sigma_radps": 0.0, "slip_sigma": 0.0,
                                   "fix_gate": {"correlation_model": "producer"}})
    z1 = np.array([15.0, 2.0, -0.6])
    cov1 = _partial_rim_cov(z1)
    obs1 = CraterObservations(0.0, z1[None], cov1[None], [6.0], [0.3], [0.3], [0.9])
    upd = CraterUpdate(EkfConfig(), kind_named("craters"))
    s = be._s.copy()
    upd.update(s, obs1)
    assert s.n_landmarks == 1
    prior = s.copy()
    z2 = z1 + np.array([0.4, -0.2, 0.05])  # within the gate of the long partial-rim covariance
    obs2 = CraterObservations(2.0, z2[None], cov1[None], [6.2], [0.3], [0.3], [0.9])
    rep = upd.update(s, obs2)
    assert rep.n_associated == 1 and s.n_landmarks == 1
    x0 = (prior.p_world, prior.R_world_base, prior.l_world[0])
    eps = 1e-6
    H = np.column_stack([(_h(_perturb(x0, d)) - _h(_perturb(x0, -d))) / (2 * eps) for d in np.eye(9) * eps])
    P = prior.P
    S = H @ P @ H.T + cov1
    K = P @ H.T @ np.linalg.inv(S)
    dx = K @ (z2 - _h(x0))
    np.testing.assert_allclose(s.p_world, prior.p_world + dx[:3], atol=1e-7)
    np.testing.assert_allclose(s.l_world[0], prior.l_world[0] + dx[6:9], atol=1e-7)
    np.testing.assert_allclose(s.R_world_base, exp_so3(dx[3:6]) @ prior.R_world_base, atol=1e-7)
    I_KH = np.eye(9) - K @ H
    np.testing.assert_allclose(s.P, I_KH @ P @ I_KH.T + K @ cov1 @ K.T, rtol=1e-6, atol=1e-9)


def test_craters_share_the_estimated_calibration_or_consider_it():
    """With the calibration variable C(0), crater factors are on it as the rocks are; with
    ``share_calibration`` off they stay C++ and take its prior into their covariance
    (J_c Sigma_c J_c^T)."""
    from fgslam.smoother.factors import calibration_cov
    from reloc.calibration import CalibrationConfig

    cal = CalibrationConfig(yaw_sigma_deg=0.15, scale_sigma=0.003)
    ck = gtsam.symbol("c", 0)
    z = np.array([15.0, 3.0, -0.5])
    layer = CraterLandmarks(SmootherConfig(calibration=cal, kinds={"craters": {"share_calibration": False}}),
                            kind_named("craters"), ck)
    assert layer.calib_key is None and isinstance(layer._point_factor(0, 0, z, np.eye(3)), gtsam.BearingRangeFactor3D)
    np.testing.assert_allclose(calibration_cov(z, layer._consider_cov)[0],
                               calibration_cov(z, np.diag(cal.prior_sigmas() ** 2))[0])
    shared = CraterLandmarks(SmootherConfig(calibration=cal), kind_named("craters"), ck)
    f = shared._point_factor(0, 0, z, np.eye(3))
    assert shared._consider_cov is None and isinstance(f, gtsam.CustomFactor) and ck in f.keys()  # noqa: SIM118
