"""Custom factor maths: the exact SE(2)-on-Pose3 fix residual and the rock point factor.

GTSAM's Pose3 tangent is ``xi = [omega (3, rad), v (3, m)]`` in the body frame with the right
perturbation ``T_true = T @ Exp(xi)``. The back-end protocol's covariance (reloc.backend) is over
``[dp_world, dtheta_world]``; :func:`cov_gtsam_to_world` / :func:`cov_world_to_gtsam` convert.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from reloc.geometry import skew, wrap_angle


def _swap(R: np.ndarray) -> np.ndarray:
    A = np.zeros((6, 6))
    A[:3, 3:] = R
    A[3:, :3] = R
    return A


def cov_gtsam_to_world(R_world_base: np.ndarray, cov_body: np.ndarray) -> np.ndarray:
    """GTSAM body-frame [rot, trans] (6, 6) covariance -> protocol [dp_world, dtheta_world] (6, 6)."""
    A = _swap(R_world_base)
    return A @ cov_body @ A.T


def cov_world_to_gtsam(R_world_base: np.ndarray, cov_world: np.ndarray) -> np.ndarray:
    """Protocol [dp_world, dtheta_world] (6, 6) covariance -> GTSAM body-frame [rot, trans] (6, 6)."""
    A = _swap(R_world_base)
    return A.T @ cov_world @ A


def adjoint(T: np.ndarray) -> np.ndarray:
    """(4, 4) pose -> (6, 6) adjoint in GTSAM's [rot, trans] ordering."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = skew(t) @ R
    return Ad


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def se2_residual(T_world_base: np.ndarray, xyyaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residual (3,) [x - x_fix, y - y_fix, wrap(yaw - yaw_fix)] of a Pose3 against a planar fix,
    and its (3, 6) Jacobian w.r.t. the pose's right perturbation [omega, v]; with a fix height
    (``xyyaw`` of 4: x, y, yaw, z) also z - z_fix, (4,) and (4, 6).

    yaw is the heading of base_link's x axis projected on the world xy plane, so the residual is
    exact on sloped ground (roll/pitch, and z without a height, are left free, unlike a Pose3
    prior with huge sigmas).
    """
    R, p = T_world_base[:3, :3], T_world_base[:3, 3]
    a = R[:, 0]
    n2 = a[0] ** 2 + a[1] ** 2
    n = len(xyyaw)
    r = np.array([p[0] - xyyaw[0], p[1] - xyyaw[1], wrap_angle(float(np.arctan2(a[1], a[0]) - xyyaw[2]))]
                 + ([p[2] - xyyaw[3]] if n == 4 else []))
    H = np.zeros((n, 6))
    H[:2, 3:] = R[:2, :]  # dp = R dv
    M = -R @ skew(np.array([1.0, 0.0, 0.0]))  # da = R [omega]x e1 = -R [e1]x omega
    H[2, :3] = (a[0] * M[1] - a[1] * M[0]) / n2
    if n == 4:
        H[3, 3:] = R[2, :]
    return r, H


def fix_residual(
    T_world_kf: np.ndarray, T_kf_meas: np.ndarray, xyyaw: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residual (3,) of the pose ``T_world_kf @ T_kf_meas`` (keyframe pose composed with the
    odometry to the fix time) against a planar fix, and its (3, 6) Jacobian w.r.t. the keyframe
    ((4,) and (4, 6) against a fix with a height, :func:`se2_residual`)."""
    r, H_meas = se2_residual(T_world_kf @ T_kf_meas, xyyaw)
    # T_kf Exp(xi) T_rel = T_kf T_rel Exp(Ad(T_rel^-1) xi)
    return r, H_meas @ adjoint(inverse(T_kf_meas))


def fix_covariance(
    T_world_meas: np.ndarray, cov_rel_body: np.ndarray, cov_xyyaw: np.ndarray
) -> np.ndarray:
    """(3, 3) covariance of the fix residual: the fix's own plus the odometry's from the keyframe
    to the fix time (``cov_rel_body`` (6, 6), GTSAM body frame at the fix time); (4, 4) for a fix
    with a height (``cov_xyyaw`` (4, 4))."""
    _, H = se2_residual(T_world_meas, np.zeros(len(cov_xyyaw)))
    return cov_xyyaw + H @ cov_rel_body @ H.T


def make_fix_factor(
    key: int, T_kf_meas: np.ndarray, xyyaw: np.ndarray, cov: np.ndarray, cauchy_k: float,
    offset_key: int | None = None, offset_rows: np.ndarray | None = None,
) -> gtsam.CustomFactor:
    """CustomFactor on Pose3 ``key``: exact (x, y, yaw) residual at ``T_kf_meas`` (4, 4) after the
    keyframe, covariance ``cov`` (3, 3), under a Cauchy kernel of scale ``cauchy_k``; (x, y, yaw, z)
    with ``xyyaw`` of 4 and ``cov`` (4, 4). With ``offset_key`` (a Vector3, the fix source's shared
    error ``o``) the measured fix is the pose's plus ``offset_rows @ o`` (``offset_rows`` (m, 3):
    the identity on (x, y, yaw), and a height's row ``g``, the terrain's gradient), so the residual
    is ``h(T) + offset_rows @ o - fix``."""
    T_rel = np.array(T_kf_meas, dtype=float)
    target = np.array(xyyaw, dtype=float)
    base = gtsam.noiseModel.Gaussian.Covariance(np.array(cov, dtype=float))
    model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k), base)
    if offset_key is None:
        def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
            T = values.atPose3(this.keys()[0]).matrix()
            r, J = fix_residual(T, T_rel, target)
            if H is not None:
                H[0] = J
            return r

        return gtsam.CustomFactor(model, [key], error)
    G = np.array(offset_rows, dtype=float)
    if G.shape != (len(target), 3):
        raise ValueError(f"offset_rows must be ({len(target)}, 3) for this fix, got {G.shape}")

    def error_offset(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        k = this.keys()
        r, J = fix_residual(values.atPose3(k[0]).matrix(), T_rel, target)
        if H is not None:
            H[0], H[1] = J, G
        return r + G @ values.atVector(k[1])

    return gtsam.CustomFactor(model, [key, offset_key], error_offset)


def make_gauss_markov_factor(prev_key: int, key: int, rho: float, cov: np.ndarray) -> gtsam.CustomFactor:
    """First-order Gauss-Markov step between two vector variables: ``x_key = rho x_prev + w``,
    ``w ~ N(0, cov)``; residual ``x_key - rho x_prev``. Linear (a CustomFactor: it comes once per
    applied fix, so its Python costs nothing that matters)."""
    C = np.array(cov, dtype=float)
    n = len(C)
    J_prev, J_new = -float(rho) * np.eye(n), np.eye(n)
    model = gtsam.noiseModel.Gaussian.Covariance(C)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        k = this.keys()
        if H is not None:
            H[0], H[1] = J_prev, J_new
        return values.atVector(k[1]) - float(rho) * values.atVector(k[0])

    return gtsam.CustomFactor(model, [prev_key, key], error)


def point_factor_covariance(z_base: np.ndarray, cov_base: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of a bearing-range measurement [bearing tangent (2), range (1)] of a point
    ``z_base`` (3,) with base-frame covariance ``cov_base`` (3, 3). The bearing tangent is in the
    basis of ``gtsam.Unit3(z_base)``, as GTSAM's BearingRange error uses."""
    r = float(np.linalg.norm(z_base))
    u = z_base / r
    B = gtsam.Unit3(z_base).basis()
    J = np.vstack([B.T / r, u[None, :]])
    C = J @ cov_base @ J.T
    return 0.5 * (C + C.T)


def make_point_factor(
    pose_key: int, point_key: int, z_base: np.ndarray, cov_base: np.ndarray, huber_k: float
) -> gtsam.BearingRangeFactor3D:
    """Rock seen at ``z_base`` (3,) m in base_link with covariance ``cov_base`` (3, 3): a C++
    BearingRangeFactor3D (Pose3 -> Point3) whose bearing/range covariance is the exact linear image
    of ``cov_base``, under a Huber kernel. Stereo noise is nearly constant in bearing and grows with
    range squared, so this parameterisation fits it better than a Cartesian one."""
    z = np.asarray(z_base, dtype=float)
    base = gtsam.noiseModel.Gaussian.Covariance(point_factor_covariance(z, cov_base))
    model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), base)
    return gtsam.BearingRangeFactor3D(pose_key, point_key, gtsam.Unit3(z), float(np.linalg.norm(z)), model)


def calibrated_point_residual(
    T_world_kf: np.ndarray, l_world: np.ndarray, c: np.ndarray, z_kf: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residual (3,) ``h - z`` of a rock seen at ``z_kf`` (3,) in the keyframe's base_link, with
    ``h = (1 + c[3]) Exp(c[:3]) R^T (l - t)`` (calibration ``c`` (4,): rotation error, scale - 1),
    and its Jacobians w.r.t. the pose's right perturbation [omega, v] (3, 6), the point (3, 3)
    and the calibration (3, 4).

    With ``q = R^T (l - t)``, ``E = Exp(w)``, ``y = E q``, ``s = 1 + c[3]``:
    ``H_pose = [s E [q]x, -s E]`` (``q(T Exp(xi)) ~ q + [q]x omega - v``), ``H_point = s E R^T``,
    ``H_c = [-s [y]x J_l(w), y]`` (``Exp(w + dw) = Exp(J_l(w) dw) Exp(w)`` to first order). Written
    on Python floats, one array at the end: it runs once per rock factor per linearization (a
    batch step of the fixed-lag smoother relinearizes all of them), and 3x3 numpy operations
    cost more in call overhead than in arithmetic (15 us instead of 40 us a call, measured).
    """
    (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2) = T_world_kf[:3].tolist()
    lx, ly, lz = l_world.tolist()
    z0, z1, z2 = z_kf.tolist()
    w0, w1, w2, c3 = c.tolist()
    d0, d1, d2 = lx - t0, ly - t1, lz - t2
    q0 = r00 * d0 + r10 * d1 + r20 * d2  # q = R^T (l - t)
    q1 = r01 * d0 + r11 * d1 + r21 * d2
    q2 = r02 * d0 + r12 * d1 + r22 * d2
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-12:  # series: E = I + K + K^2 / 2, J_l = I + K / 2 + K^2 / 6
        a, b, g = 1.0, 0.5, 1.0 / 6.0
    else:  # E = I + a K + b K^2, J_l = I + b K + g K^2 (K = [w]x)
        th = math.sqrt(th2)
        sn, cs = math.sin(th), math.cos(th)
        a, b, g = sn / th, (1.0 - cs) / th2, (th - sn) / (th2 * th)
    k00, k11, k22 = w0 * w0 - th2, w1 * w1 - th2, w2 * w2 - th2  # K^2 = w w^T - |w|^2 I
    k01, k02, k12 = w0 * w1, w0 * w2, w1 * w2
    E = ((1.0 + b * k00, -a * w2 + b * k01, a * w1 + b * k02),
         (a * w2 + b * k01, 1.0 + b * k11, -a * w0 + b * k12),
         (-a * w1 + b * k02, a * w0 + b * k12, 1.0 + b * k22))
    Jl = ((1.0 + g * k00, -b * w2 + g * k01, b * w1 + g * k02),
          (b * w2 + g * k01, 1.0 + g * k11, -b * w0 + g * k12),
          (-b * w1 + g * k02, b * w0 + g * k12, 1.0 + g * k22))
    s = 1.0 + c3
    y0, y1, y2 = y = [e0 * q0 + e1 * q1 + e2 * q2 for e0, e1, e2 in E]
    flat = [s * y0 - z0, s * y1 - z1, s * y2 - z2]
    for e0, e1, e2 in E:  # H_pose row: s E [q]x, -s E
        flat += (s * (e1 * q2 - e2 * q1), s * (e2 * q0 - e0 * q2), s * (e0 * q1 - e1 * q0), -s * e0, -s * e1, -s * e2)
    for e0, e1, e2 in E:  # H_point row: s E R^T
        flat += (s * (e0 * r00 + e1 * r01 + e2 * r02), s * (e0 * r10 + e1 * r11 + e2 * r12),
                 s * (e0 * r20 + e1 * r21 + e2 * r22))
    for (m0, m1, m2), yi in zip(((0.0, -y2, y1), (y2, 0.0, -y0), (-y1, y0, 0.0)), y):  # H_c row: -s [y]x J_l, y
        flat += [-s * (m0 * Jl[0][j] + m1 * Jl[1][j] + m2 * Jl[2][j]) for j in range(3)]
        flat.append(yi)
    out = np.array(flat)
    return out[:3], out[3:21].reshape(3, 6), out[21:30].reshape(3, 3), out[30:].reshape(3, 4)


def calibration_cov(z: np.ndarray, cov_c: np.ndarray) -> np.ndarray:
    """(n, 3, 3): the covariance that calibration ``c`` ~ N(0, ``cov_c`` (4, 4)) adds to points
    ``z`` (n, 3) seen in base_link, ``J_c cov_c J_c^T`` with ``J_c = [-[z]x, z]`` (the Jacobian
    of :func:`calibrated_point_residual` at ``c = 0``)."""
    z = np.asarray(z, dtype=float).reshape(-1, 3)
    J = np.empty((len(z), 3, 4))
    J[:, :, :3] = -skew(z)
    J[:, :, 3] = z
    return J @ cov_c @ np.swapaxes(J, 1, 2)


def make_calibrated_point_factor(
    pose_key: int, point_key: int, calib_key: int, z_kf: np.ndarray, cov_kf: np.ndarray, huber_k: float
) -> gtsam.CustomFactor:
    """Rock seen at ``z_kf`` (3,) with covariance ``cov_kf`` (3, 3) from keyframe ``pose_key``,
    through the stereo calibration ``calib_key`` (Vector4): a Cartesian CustomFactor under a
    Huber kernel (see :func:`calibrated_point_residual`)."""
    z = np.array(z_kf, dtype=float)
    base = gtsam.noiseModel.Gaussian.Covariance(np.array(cov_kf, dtype=float))
    model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), base)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        k = this.keys()
        r, Hp, Hl, Hc = calibrated_point_residual(values.atPose3(k[0]).matrix(), values.atPoint3(k[1]),
                                                  values.atVector(k[2]), z)
        if H is not None:
            H[0], H[1], H[2] = Hp, Hl, Hc
        return r

    return gtsam.CustomFactor(model, [pose_key, point_key, calib_key], error)
