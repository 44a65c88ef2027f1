"""Numerical-derivative checks of every Jacobian: motion model, landmark measurement and
initialisation, planar fix, roll/pitch pseudo-measurement."""

from __future__ import annotations

import numpy as np
import pytest

from ekf.config import MotionNoiseConfig
from ekf.motion import propagate, split_step
from ekf.updates import E_Z, attitude_model, fix_model, gravity_basis
from reloc.geometry import exp_so3, log_so3, wrap_angle
from reloc.landmark_model import init_jacobians, point_in_base, point_jacobians, point_to_world
from reloc.odometry import OdometryStep

EPS = 1e-6


def random_pose(rng):
    return rng.normal(0, 5, 3), exp_so3(rng.normal(0, 0.3, 3))


def perturb(p, R, d):
    return p + d[:3], exp_so3(d[3:]) @ R


def numeric_jacobian(fun, dim, m):
    J = np.zeros((m, dim))
    for i in range(dim):
        d = np.zeros(dim)
        d[i] = EPS
        J[:, i] = (fun(d) - fun(-d)) / (2 * EPS)
    return J


@pytest.mark.parametrize("seed", range(5))
def test_motion_jacobian(seed):
    rng = np.random.default_rng(seed)
    p, R = random_pose(rng)
    R0 = exp_so3(rng.normal(0, 0.2, 3))
    R1 = R0 @ exp_so3(rng.normal(0, 0.05, 3))
    step = OdometryStep(0.0, 0.1, rng.uniform(-0.5, 1.0), 0.1, R0, R1, np.zeros(3))
    cfg = MotionNoiseConfig()
    p1, R1n, F, Q = propagate(p, R, step, cfg)

    def f(d):
        pp, RR = perturb(p, R, d)
        q1, Q1, _, _ = propagate(pp, RR, step, cfg)
        return np.concatenate([q1 - p1, log_so3(Q1 @ R1n.T)])

    assert np.allclose(numeric_jacobian(f, 6, 6), F, atol=1e-6)
    assert np.allclose(Q, Q.T) and np.all(np.linalg.eigvalsh(Q) > 0)


def test_split_step_composes():
    rng = np.random.default_rng(3)
    R0 = exp_so3(rng.normal(0, 0.2, 3))
    step = OdometryStep(1.0, 1.1, 0.3, 0.0, R0, R0 @ exp_so3([0.01, -0.02, 0.05]), np.zeros(3))
    a, b = split_step(step, 1.04)
    assert a.t1 == b.t0 == 1.04
    assert np.allclose(a.R_ref_base0 @ a.dR_base @ b.dR_base, step.R_ref_base1, atol=1e-12)
    assert np.allclose(log_so3(a.dR_base), 0.4 * log_so3(step.dR_base), atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_point_measurement_jacobians(seed):
    rng = np.random.default_rng(seed)
    p, R = random_pose(rng)
    L = p + rng.normal(0, 4, (4, 3))
    H_pose, H_l = point_jacobians(R, p, L)
    for j in range(4):
        def f_pose(d, j=j):
            pp, RR = perturb(p, R, d)
            return point_in_base(RR, pp, L[j])[0]

        def f_l(d, j=j):
            return point_in_base(R, p, L[j] + d)[0]

        assert np.allclose(numeric_jacobian(f_pose, 6, 3), H_pose[j], atol=1e-6)
        assert np.allclose(numeric_jacobian(f_l, 3, 3), H_l, atol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_landmark_init_jacobians_and_round_trip(seed):
    rng = np.random.default_rng(seed)
    p, R = random_pose(rng)
    z = rng.normal(0, 4, (3, 3))
    Rz = np.stack([np.diag(rng.uniform(0.01, 0.1, 3)) for _ in range(3)])
    l, cov = point_to_world(R, p, z, Rz)
    assert np.allclose(point_in_base(R, p, l), z, atol=1e-12)
    assert np.allclose(cov, R @ Rz @ R.T)
    G_pose, G_z = init_jacobians(R, z)
    for j in range(3):
        def f(d, j=j):
            pp, RR = perturb(p, R, d)
            return point_to_world(RR, pp, z[j], Rz[j])[0][0]

        assert np.allclose(numeric_jacobian(f, 6, 3), G_pose[j], atol=1e-6)
    assert np.allclose(G_z, R)


@pytest.mark.parametrize("seed", range(5))
def test_fix_jacobian(seed):
    rng = np.random.default_rng(seed)
    p, R = random_pose(rng)
    h, H = fix_model(p, R)

    def f(d):
        pp, RR = perturb(p, R, d)
        hh, _ = fix_model(pp, RR)
        out = hh - h
        out[2] = wrap_angle(out[2])
        return out

    assert np.allclose(numeric_jacobian(f, 6, 3), H, atol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_attitude_jacobian(seed):
    rng = np.random.default_rng(seed)
    _, R = random_pose(rng)
    R_ref = exp_so3([0.0, 0.0, 0.7]) @ exp_so3(rng.normal(0, 0.01, 3)) @ R  # yaw offset + small error
    _, H = attitude_model(R, R_ref)

    B = gravity_basis(R.T @ E_Z)  # the innovation basis is fixed at the linearisation point

    def f(d):
        _, RR = perturb(np.zeros(3), R, d)
        return B @ (RR.T @ E_Z)

    Jn = numeric_jacobian(f, 6, 2)
    assert np.allclose(Jn, H, atol=1e-4)
    # the pure yaw offset is invisible
    nu_yaw, _ = attitude_model(R, exp_so3([0.0, 0.0, 1.3]) @ R)
    assert np.allclose(nu_yaw, 0.0, atol=1e-12)
