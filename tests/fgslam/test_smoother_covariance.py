"""The one-pass Bayes-tree marginals equal gtsam.Marginals, key by key, for keyframes and
landmarks, in full and fixed-lag mode."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from fgslam.smoother import Isam2Smoother, SmootherConfig
from fgslam.smoother.synthetic import SyntheticConfig, drive, simulate_synthetic


@pytest.mark.parametrize("lag_s", [0.0, 20.0])
def test_tree_marginals_equal_gtsam_marginals(lag_s):
    run = simulate_synthetic(SyntheticConfig(seed=4, duration_s=40.0, rock_density_per_m2=0.4))
    sm = Isam2Smoother(run.initial_pose, SmootherConfig(fixed_lag_s=lag_s))
    drive(sm, run.measurements)
    s = sm.solver
    keys = [k for k in s.theta().keys() if s.alive(k)]  # noqa: SIM118 (gtsam.Values)
    assert sum(gtsam.Symbol(k).chr() == ord("x") for k in keys) > 10
    assert sum(gtsam.Symbol(k).chr() == ord("l") for k in keys) > 10
    src = s.factors()
    graph = gtsam.NonlinearFactorGraph()
    for i in range(src.size()):
        if src.exists(i):
            graph.add(src.at(i))
    ref = gtsam.Marginals(graph, (s.ifls if s.fixed_lag else s.isam).calculateEstimate())
    for k, C in zip(keys, s.marginal_covs(keys)):
        C_ref = np.asarray(ref.marginalCovariance(k))
        np.testing.assert_allclose(C, C_ref, rtol=1e-7, atol=1e-12 * np.abs(C_ref).max())
    assert s.marginal_covs([X(0)] if s.alive(X(0)) else keys[:1])
