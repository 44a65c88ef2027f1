"""The Monte Carlo start: a draw from the start's claimed prior, in the back-ends' error convention."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fgslam.inputs import start_drawn_from_prior
from reloc.backend import PoseEstimate


def test_start_errors_have_the_claimed_covariance_in_the_backend_convention():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [1.1, 0.05, -0.03]).as_matrix()
    T[:3, 3] = [3.0, -2.0, 0.5]
    A = np.random.default_rng(7).standard_normal((6, 6))
    cov = 1e-4 * (A @ A.T + np.eye(6))
    start = PoseEstimate(12.5, T, cov)
    errs = []
    for seed in range(4000):
        d = start_drawn_from_prior(start, seed)
        assert d.t == 12.5 and d.cov is cov
        # reloc.backend: R_true = Exp(dtheta) R_est, p_true = p_est + dp
        dtheta = Rotation.from_matrix(T[:3, :3] @ d.T_world_base[:3, :3].T).as_rotvec()
        errs.append(np.concatenate([T[:3, 3] - d.T_world_base[:3, 3], dtheta]))
    errs = np.array(errs)
    assert np.all(np.abs(errs.mean(axis=0)) < 4 * np.sqrt(np.diag(cov) / len(errs)))
    np.testing.assert_allclose(np.cov(errs.T), cov, atol=0.1 * np.max(np.diag(cov)))
    # seeded: the same seed gives the same start
    np.testing.assert_array_equal(start_drawn_from_prior(start, 3).T_world_base, start_drawn_from_prior(start, 3).T_world_base)
