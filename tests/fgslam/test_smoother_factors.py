"""Numerical-derivative and statistical checks of every custom factor / model of the smoother."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X
from scipy.spatial.transform import Rotation

from fgslam.smoother.config import OdometryNoiseConfig
from fgslam.smoother.factors import (
    cov_gtsam_to_world,
    cov_world_to_gtsam,
    fix_residual,
    make_fix_factor,
    make_point_factor,
    point_factor_covariance,
    se2_residual,
)
from fgslam.smoother.odometry_factors import OdometryAccumulator, gravity_factor, step_motion
from reloc.odometry import OdometryStep


def _random_pose(rng: np.random.Generator, tilt: float = 0.3) -> np.ndarray:
    ypr = [rng.uniform(-np.pi, np.pi), rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt)]
    return gtsam.Pose3(gtsam.Rot3.Ypr(*ypr), rng.normal(0, 5, 3)).matrix()


def _numerical_jacobian(f, T: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    P = gtsam.Pose3(T)
    cols = []
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        cols.append((f(P.retract(d).matrix()) - f(P.retract(-d).matrix())) / (2 * eps))
    return np.column_stack(cols)


@pytest.mark.parametrize("seed", range(5))
def test_fix_residual_jacobian_matches_central_differences(seed):
    rng = np.random.default_rng(seed)
    T_kf, T_rel = _random_pose(rng), _random_pose(rng, 0.05)
    T_rel[:3, 3] *= 0.1
    fix = np.array([T_kf[0, 3] + 1.0, T_kf[1, 3] - 0.5, 0.3])
    r, H = fix_residual(T_kf, T_rel, fix)
    Hn = _numerical_jacobian(lambda T: fix_residual(T, T_rel, fix)[0], T_kf)
    np.testing.assert_allclose(H, Hn, atol=1e-7)
    # the CustomFactor evaluates the same residual and, through gtsam, the same Jacobian
    factor = make_fix_factor(X(0), T_rel, fix, np.diag([0.25, 0.25, 0.01]), 2.0)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(T_kf))
    np.testing.assert_allclose(factor.unwhitenedError(values), r, atol=1e-12)
    lin = factor.linearize(values)
    A, _b = lin.jacobian()
    Wn = np.linalg.cholesky(np.linalg.inv(np.diag([0.25, 0.25, 0.01]))).T
    # robust weighting scales rows uniformly; compare directions through the whitened Jacobian
    scale = np.linalg.norm(A) / np.linalg.norm(Wn @ H)
    np.testing.assert_allclose(A, scale * (Wn @ H), atol=1e-6)


def test_se2_residual_is_exact_on_sloped_ground():
    """A tilted, raised pose whose planar part matches the fix has zero residual (a Pose3 prior with
    zero roll/pitch/z would not), and yaw is the heading of base_link x projected on the plane."""
    R = Rotation.from_euler("ZYX", [0.7, 0.25, -0.2]).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [3.0, -2.0, 1.5]
    yaw = np.arctan2(R[1, 0], R[0, 0])
    r, _ = se2_residual(T, np.array([3.0, -2.0, yaw]))
    np.testing.assert_allclose(r, 0.0, atol=1e-12)
    r, _ = se2_residual(T, np.array([3.0, -2.0, yaw + 2 * np.pi - 0.1]))
    assert r[2] == pytest.approx(0.1)  # wrapped


def test_point_factor_covariance_is_linear_image_of_base_covariance(rng):
    z = np.array([4.0, 1.0, -0.4])
    A = rng.normal(size=(3, 3))
    C = A @ A.T * 0.01 + np.eye(3) * 1e-3
    f = make_point_factor(X(0), L(0), z, C, huber_k=1e9)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3())
    d = np.array([2e-5, -1e-5, 3e-5])
    values.insert(L(0), z + d)
    J = np.linalg.cholesky(point_factor_covariance(z, C))
    # error ~ J_meas d, whose covariance under d ~ N(0, C) is point_factor_covariance
    Jm = np.linalg.solve(J, f.unwhitenedError(values))
    B = gtsam.Unit3(z).basis()
    r = np.linalg.norm(z)
    Jz = np.vstack([B.T / r, z[None, :] / r])
    np.testing.assert_allclose(f.unwhitenedError(values), Jz @ d, atol=1e-8)
    # whitened errors of samples drawn from C are chi2(3): mean ~ 3
    samples = rng.multivariate_normal(np.zeros(3), C, 3000) * 1e-2  # small: linear regime
    Cs = C * 1e-4
    fs = make_point_factor(X(0), L(0), z, Cs, huber_k=1e9)
    d2 = []
    for s in samples[:400]:
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose3())
        v.insert(L(0), z + s)
        e = fs.unwhitenedError(v)
        d2.append(e @ np.linalg.solve(point_factor_covariance(z, Cs), e))
    assert 2.6 < np.mean(d2) < 3.4
    assert np.all(np.isfinite(Jm))


def test_point_factor_jacobians_match_numerical(rng):
    T = _random_pose(rng)
    l_world = T[:3, :3] @ np.array([5.0, 1.0, 0.2]) + T[:3, 3]
    f = make_point_factor(X(0), L(0), np.array([5.0, 1.0, 0.2]), np.eye(3) * 0.01, huber_k=1e9)

    def err(Tp, lp=l_world):
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose3(Tp))
        v.insert(L(0), lp)
        return f.unwhitenedError(v)

    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(T))
    v.insert(L(0), l_world)
    A, _ = f.linearize(v).jacobian()
    W = np.linalg.cholesky(np.linalg.inv(point_factor_covariance(np.array([5.0, 1.0, 0.2]), np.eye(3) * 0.01))).T
    Hp = _numerical_jacobian(err, T)
    Hl = np.column_stack([(err(T, l_world + e) - err(T, l_world - e)) / 2e-6 for e in np.eye(3) * 1e-6])
    # at zero residual (GTSAM's Unit3 local-coordinate derivative is first order away from it)
    np.testing.assert_allclose(A, W @ np.hstack([Hp, Hl]), rtol=1e-5, atol=1e-5)


def test_gravity_factor_constrains_roll_pitch_not_yaw():
    R = Rotation.from_euler("ZYX", [0.4, 0.1, -0.05]).as_matrix()
    R_imu = Rotation.from_euler("ZYX", [1.9, 0.1, -0.05]).as_matrix()  # yaw drifted, gravity the same
    f = gravity_factor(X(0), R_imu, 0.01)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(gtsam.Rot3(R), np.zeros(3)))
    assert np.linalg.norm(f.unwhitenedError(v)) < 1e-9
    v2 = gtsam.Values()
    v2.insert(X(0), gtsam.Pose3(gtsam.Rot3(Rotation.from_euler("ZYX", [0.4, 0.15, -0.05]).as_matrix()), np.zeros(3)))
    assert np.linalg.norm(f.unwhitenedError(v2)) == pytest.approx(0.05, rel=0.05)


def test_covariance_conversion_matches_sampled_perturbations(rng):
    T = _random_pose(rng)
    A = rng.normal(size=(6, 6)) * 0.02
    C_body = A @ A.T
    errs = []
    for xi in rng.multivariate_normal(np.zeros(6), C_body, 4000):
        Tt = (gtsam.Pose3(T) * gtsam.Pose3.Expmap(xi)).matrix()
        dp = Tt[:3, 3] - T[:3, 3]
        dth = Rotation.from_matrix(Tt[:3, :3] @ T[:3, :3].T).as_rotvec()
        errs.append(np.concatenate([dp, dth]))
    C_emp = np.cov(np.array(errs).T)
    C_world = cov_gtsam_to_world(T[:3, :3], C_body)
    np.testing.assert_allclose(C_emp, C_world, atol=3e-5 + 0.1 * np.abs(C_world).max())
    np.testing.assert_allclose(cov_world_to_gtsam(T[:3, :3], C_world), C_body, atol=1e-12)


def test_accumulated_odometry_covariance_matches_monte_carlo(rng):
    """Compose 15 noisy steps; the propagated covariance matches the sampled spread."""
    cfg = OdometryNoiseConfig()
    R0 = np.eye(3)
    steps = []
    for i in range(15):
        R1 = R0 @ Rotation.from_rotvec([0.001, 0.002, 0.01]).as_matrix()
        steps.append(OdometryStep(i * 0.1, (i + 1) * 0.1, 0.5, 0.1, R0, R1, np.zeros(3)))
        R0 = R1
    acc = OdometryAccumulator(0.0)
    for s in steps:
        acc.push(s, cfg)
    samples = []
    for _ in range(800):
        T = np.eye(4)
        for s in steps:
            dT, Q = step_motion(s, cfg)
            T = (gtsam.Pose3(T) * gtsam.Pose3(dT) * gtsam.Pose3.Expmap(np.sqrt(np.diag(Q)) * rng.standard_normal(6))).matrix()
        samples.append(gtsam.Pose3.Logmap(gtsam.Pose3(acc.T_kf_now).between(gtsam.Pose3(T))))
    C_emp = np.cov(np.array(samples).T)
    d = np.sqrt(np.diag(acc.cov))
    np.testing.assert_allclose(C_emp / np.outer(d, d), acc.cov / np.outer(d, d), atol=0.12)


def test_batched_fix_residuals_equal_one_by_one(rng):
    from fgslam.smoother.factors import fix_residual
    from fgslam.smoother.fixes import FixRecord, residual_d2_many
    from reloc.measurements import GlobalFix

    recs, T_kf = [], []
    for i in range(7):
        A = rng.normal(size=(3, 3))
        fix = GlobalFix(t_meas=float(i), t_recv=i + 1.0, x_m=float(rng.normal()), y_m=float(rng.normal()),
                        yaw_rad=float(rng.uniform(-3.1, 3.1)), cov_xyyaw=A @ A.T + 0.1 * np.eye(3))
        T_rel = np.eye(4)
        T_rel[:3, :3] = Rotation.from_rotvec(rng.normal(scale=0.2, size=3)).as_matrix()
        T_rel[:3, 3] = rng.normal(size=3)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        T[:3, 3] = rng.normal(size=3)
        recs.append(FixRecord(fix, i, X(i), T_rel, fix.cov_xyyaw + 0.05 * np.eye(3), i))
        T_kf.append(T)
    expected = []
    for r, T in zip(recs, T_kf):  # the fix factor's own residual, one record at a time
        res, _ = fix_residual(T, r.T_kf_meas, r.fix.xyyaw)
        expected.append(res @ np.linalg.solve(r.cov, res))
    assert np.allclose(residual_d2_many(recs, np.array(T_kf)), expected, rtol=1e-12)
    assert residual_d2_many([], np.zeros((0, 4, 4))).shape == (0,)


@pytest.mark.parametrize("c", [
    [0.002, -0.003, 0.004, 0.003],  # rotation (rad), scale - 1: calibration-sized
    [0.4, -0.7, 0.2, -0.05],  # far from 0: the closed forms of Exp and its left Jacobian
    [3e-8, -2e-8, 1e-8, 0.001],  # below 1e-6 rad: their series
])
def test_calibrated_point_factor_jacobians_match_numerical(rng, c):
    from gtsam.symbol_shorthand import C

    from fgslam.smoother.factors import calibrated_point_residual, make_calibrated_point_factor

    T = _random_pose(rng)
    l_world = T[:3, :3] @ np.array([5.0, 1.0, 0.2]) + T[:3, 3]
    c = np.array(c)
    z = np.array([5.1, 0.9, 0.25])
    r, Hp, Hl, Hc = calibrated_point_residual(T, l_world, c, z)
    num_p = _numerical_jacobian(lambda Tp: calibrated_point_residual(Tp, l_world, c, z)[0], T)
    num_l = np.column_stack([(calibrated_point_residual(T, l_world + e, c, z)[0]
                              - calibrated_point_residual(T, l_world - e, c, z)[0]) / 2e-6 for e in np.eye(3) * 1e-6])
    num_c = np.column_stack([(calibrated_point_residual(T, l_world, c + e, z)[0]
                              - calibrated_point_residual(T, l_world, c - e, z)[0]) / 2e-7 for e in np.eye(4) * 1e-7])
    np.testing.assert_allclose(Hp, num_p, atol=1e-5)
    np.testing.assert_allclose(Hl, num_l, atol=1e-6)
    np.testing.assert_allclose(Hc, num_c, atol=1e-6)
    # no calibration: the residual is the plain point model R^T (l - t) - z
    np.testing.assert_allclose(calibrated_point_residual(T, l_world, np.zeros(4), z)[0],
                               T[:3, :3].T @ (l_world - T[:3, 3]) - z, atol=1e-12)
    f = make_calibrated_point_factor(X(0), L(0), C(0), z, np.eye(3) * 0.01, huber_k=1e9)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(T))
    v.insert(L(0), l_world)
    v.insert(C(0), c)
    np.testing.assert_allclose(f.unwhitenedError(v), r, atol=1e-12)
    A, _ = f.linearize(v).jacobian()
    np.testing.assert_allclose(A, 10.0 * np.hstack([Hp, Hl, Hc]), atol=1e-9)  # whitened by 1/0.1


def test_fix_yaw_sigma_floor_raises_only_the_yaw_and_keeps_correlations():
    from fgslam.smoother.fixes import place_fix
    from reloc.measurements import GlobalFix

    cov = np.array([[0.04, 0.01, 0.0002], [0.01, 0.09, -0.0003], [0.0002, -0.0003, 0.003**2]])
    fix = GlobalFix(1.0, 2.0, 3.0, 4.0, 0.3, cov)
    T = np.eye(4)
    _, plain = place_fix(fix, X(0), np.eye(4), np.zeros((6, 6)), T, 2.0)
    _, floored = place_fix(fix, X(0), np.eye(4), np.zeros((6, 6)), T, 2.0, yaw_sigma_floor_rad=0.05)
    np.testing.assert_allclose(plain, cov, atol=1e-12)  # no odometry in between: the fix's own
    np.testing.assert_allclose(floored[:2, :2], cov[:2, :2], atol=1e-12)
    assert floored[2, 2] == pytest.approx(0.05**2)
    assert floored[0, 2] / np.sqrt(floored[0, 0] * floored[2, 2]) == pytest.approx(cov[0, 2] / np.sqrt(cov[0, 0] * cov[2, 2]))
    _, above = place_fix(fix, X(0), np.eye(4), np.zeros((6, 6)), T, 2.0, yaw_sigma_floor_rad=0.001)
    np.testing.assert_allclose(above, cov, atol=1e-12)  # a floor below the fix's sigma changes nothing


def test_considered_calibration_covariance_is_the_spread_of_calibrated_points():
    """calibration_cov is the covariance of (1 + s) Exp(w) z over calibrations c = (w, s) drawn
    from its prior (small rotations: first order holds to < 1 %)."""
    from fgslam.smoother.factors import calibration_cov

    rng = np.random.default_rng(5)
    z = np.array([[12.0, -3.0, -0.8], [4.0, 6.0, -0.9]])
    sig = np.array([0.002, 0.002, np.deg2rad(0.15), 0.003])
    c = rng.normal(size=(200_000, 4)) * sig
    R = Rotation.from_rotvec(c[:, :3]).as_matrix()
    for i, zi in enumerate(z):
        h = (1.0 + c[:, 3])[:, None] * (R @ zi)
        want = calibration_cov(z, np.diag(sig**2))[i]
        np.testing.assert_allclose(np.cov(h.T), want, rtol=0.0, atol=0.02 * np.abs(want).max())  # MC: ~0.3 %

