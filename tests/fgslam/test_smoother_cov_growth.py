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


def _block_matrix(P):
    k = P.shape[0]
    return np.transpose(P, (0, 2, 1, 3)).reshape(6 * k, 6 * k)


def test_the_shared_growth_of_a_set_of_landmarks_is_a_covariance():
    """Growths that are positive parts of covariance differences are not ordered in time, and the
    block matrix "growth since the later of the two" built from them directly can be indefinite
    (joint distances below zero passed any set of pairs after a blind spell). The nested
    construction is positive semi-definite, each diagonal block at least the landmark's own
    growth, and equal times share the same block."""
    from fgslam.smoother.landmarks import nested_growth

    rng = np.random.default_rng(5)
    found_indefinite = False
    for trial in range(200):
        n_t = int(rng.integers(2, 6))
        times = np.sort(rng.uniform(0, 100, n_t))
        table = {}
        for t in times:  # unordered PSD growths, zero-ish for the newest
            A = rng.normal(size=(6, 3)) * rng.uniform(0.01, 1.0)
            table[float(t)] = A @ A.T

        def cov_growth(t_last):
            return np.stack([table[float(t)] for t in t_last])

        t_last = rng.choice(times, size=int(rng.integers(2, 8)))
        P = nested_growth(t_last, cov_growth)
        k = len(t_last)
        assert P.shape == (k, k, 6, 6)
        assert np.linalg.eigvalsh(_block_matrix(P)).min() >= -1e-9, trial
        for a in range(k):
            assert np.linalg.eigvalsh(P[a, a] - table[float(t_last[a])]).min() >= -1e-9
            for b in range(k):
                if t_last[a] == t_last[b]:
                    np.testing.assert_allclose(P[a, b], P[a, a])
        later = np.maximum(t_last[:, None], t_last[None, :]).ravel()
        direct = cov_growth(later).reshape(k, k, 6, 6)
        found_indefinite |= np.linalg.eigvalsh(_block_matrix(direct)).min() < -1e-6
    assert found_indefinite  # the direct construction fails where the nested one holds


def test_the_shared_pose_covariance_equals_the_block_tensor_product():
    """The joint covariance's pose part, built as one low-rank term per nested increment, is the
    product of the Jacobians with the (k, k, 6, 6) tensor of shared growths it replaces."""
    from fgslam.smoother.landmarks import nested_growth, nested_increments, shared_pose_cov

    rng = np.random.default_rng(1)
    for trial in range(50):
        times = np.sort(rng.uniform(0, 100, 5))
        table = {}
        for t in times:
            A = rng.normal(size=(6, 3))
            table[float(t)] = A @ A.T

        def cov_growth(t_last, table=table):
            return np.stack([table[float(t)] for t in t_last])

        k = int(rng.integers(1, 12))
        t_last = rng.choice(times, size=k)
        H = rng.normal(size=(k, 3, 6))
        B = rng.normal(size=(6, 6))
        P = B @ B.T
        expected = np.einsum("aip,abpq,bjq->aibj", H, P + nested_growth(t_last, cov_growth), H).reshape(3 * k, 3 * k)
        np.testing.assert_allclose(shared_pose_cov(H, P, *nested_increments(t_last, cov_growth)), expected,
                                   rtol=1e-10, atol=1e-10, err_msg=str(trial))
        np.testing.assert_allclose(shared_pose_cov(H, P), np.einsum("aip,pq,bjq->aibj", H, P, H).reshape(3 * k, 3 * k),
                                   rtol=1e-10, atol=1e-10)
