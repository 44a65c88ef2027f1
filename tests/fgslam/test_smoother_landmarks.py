"""The landmark store's fast paths give the same result as the plain ones: the batched
information fusion and the per-keyframe view cache."""

from __future__ import annotations

import copy

import numpy as np

from fgslam.smoother.config import LandmarkConfig
from fgslam.smoother.landmarks import ACTIVE, CANDIDATE, LandmarkRecord, LandmarkStore


def _spd(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, 3, 3)) * scale
    return A @ np.swapaxes(A, 1, 2) + np.eye(3) * scale**2


def _store(rng: np.random.Generator, n: int) -> LandmarkStore:
    st = LandmarkStore(LandmarkConfig())
    xyz = rng.uniform(-30.0, 30.0, (n, 3)) * np.array([1.0, 1.0, 0.02])
    for i, (p, C) in enumerate(zip(xyz, _spd(rng, n, 0.05))):
        rec = LandmarkRecord(i, p, C, 0.3, 2, 0.0, 0.0, status=ACTIVE if i % 2 else CANDIDATE)
        st.records[i] = rec
        st.live[i] = rec
    st.next_id = n
    return st


def test_batched_fusion_equals_sequential_fusion():
    rng = np.random.default_rng(3)
    st = _store(rng, 12)
    recs = list(st.live.values())
    l_new = np.array([r.xyz_world_m for r in recs]) + rng.normal(0, 0.05, (12, 3))
    c_new = _spd(rng, 12, 0.08)
    size = rng.uniform(0.1, 0.5, 12)
    seq = copy.deepcopy(recs)
    for rec, li, Ci, si in zip(seq, l_new, c_new, size):
        LandmarkStore._fuse(rec, li, Ci, float(si), 5.0)
    LandmarkStore._fuse_batch(recs, l_new, c_new, size, 5.0)
    for a, b in zip(recs, seq):
        np.testing.assert_allclose(a.xyz_world_m, b.xyz_world_m, atol=1e-12)
        np.testing.assert_allclose(a.cov_world_m2, b.cov_world_m2, atol=1e-14)
        assert (a.n_obs, a.size_sum_m, a.t_last) == (b.n_obs, b.size_sum_m, b.t_last)
    # graph landmarks keep the solver's position; candidates move towards the new detections
    assert all(np.array_equal(a.xyz_world_m, r.xyz_world_m) for a, r in zip(recs, _store(np.random.default_rng(3), 12).live.values())
               if a.status == ACTIVE)
    # the same rock twice in one batch falls back to fusing in order
    twice = copy.deepcopy(recs[:1])
    ref = copy.deepcopy(recs[0])
    LandmarkStore._fuse_batch([twice[0], twice[0]], l_new[:2], c_new[:2], size[:2], 6.0)
    LandmarkStore._fuse(ref, l_new[0], c_new[0], float(size[0]), 6.0)
    LandmarkStore._fuse(ref, l_new[1], c_new[1], float(size[1]), 6.0)
    np.testing.assert_allclose(twice[0].cov_world_m2, ref.cov_world_m2, atol=1e-14)
    assert twice[0].n_obs == ref.n_obs


def test_view_cache_gives_the_same_candidates_as_a_full_scan():
    rng = np.random.default_rng(4)
    st = _store(rng, 400)
    ref = _store(np.random.default_rng(4), 400)
    p_kf = np.array([2.0, -1.0, 0.0])
    st.set_view_cache(p_kf)
    assert 0 < len(st._view) < 400
    for _ in range(50):
        yaw = rng.uniform(-np.pi, np.pi)
        R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        p = p_kf + np.append(rng.uniform(-0.7, 0.7, 2), 0.0)  # within the cache's slack
        assert [r.lid for r in st.in_view(R, p)] == [r.lid for r in ref.in_view(R, p)]
    far = p_kf + np.array([5.0, 0.0, 0.0])  # beyond the slack: full scan again
    assert [r.lid for r in st.in_view(np.eye(3), far)] == [r.lid for r in ref.in_view(np.eye(3), far)]
    # a dropped landmark disappears at once (the cache is invalidated)
    lid = st.in_view(np.eye(3), p_kf)[0].lid
    st.drop(lid)
    assert lid not in [r.lid for r in st.in_view(np.eye(3), p_kf)]
