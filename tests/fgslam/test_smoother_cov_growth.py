"""iSAM2 gates a landmark last seen on an older keyframe with the uncertainty the pose gained
since (``landmarks.gate_with_cov_growth``): the growth is the positive part of the causal
covariances' difference, zero for the newest keyframe. That it re-finds old landmarks after a
camera blackout (which without it are mapped anew) is tested in test_fault_bench.py (cnes: iSAM2
back within 0.8x of its fault-free error, 3.1x without)."""

from __future__ import annotations

import numpy as np
from _synth_stream import make_stream

from fgslam.smoother import Isam2Smoother, SmootherConfig
from fgslam.smoother.factors import cov_world_to_gtsam


def test_growth_is_the_positive_part_of_the_covariance_difference():
    from fgslam.runner import run_backend

    stream = make_stream(seed=3, duration_s=40.0)
    sm = Isam2Smoother(stream.initial, SmootherConfig())
    run_backend(sm, stream.measurements)
    k = len(sm.kfs) - 1
    G = sm._cov_growth(np.array([sm.kfs.t[k], sm.kfs.t[0], sm.kfs.t[k // 2]]))
    assert np.allclose(G[0], 0.0)
    for i, g in zip((0, k // 2), G[1:]):
        D = sm.kfs.online_cov(k) - sm.kfs.online_cov(i)
        w, V = np.linalg.eigh(0.5 * (D + D.T))
        np.testing.assert_allclose(g, cov_world_to_gtsam(sm.T_kf[:3, :3], (V * np.maximum(w, 0)) @ V.T), atol=1e-12)
        assert np.linalg.eigvalsh(g).min() >= -1e-12
