"""Procrustes (Umeyama) similarity fits, the binomial acceptance statistic and one-to-one inliers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.stats import binom

from reloc.match_result import similarity_covariance
from reloc.procrustes import Similarity2D, rotation_2d, similarity_batch, umeyama_2d
from reloc.scoring import (
    CoarseScorer,
    chance_probability,
    log10_binomial_tail,
    log10_poisson_binomial_tail,
    score_points,
)


@settings(max_examples=120, deadline=None)
@given(
    theta=st.floats(-np.pi, np.pi),
    scale=st.floats(0.3, 3.0),
    tx=st.floats(-1e4, 1e4),
    ty=st.floats(-1e4, 1e4),
    seed=st.integers(0, 2**31 - 1),
    k=st.integers(3, 40),
)
def test_umeyama_recovers_random_similarities(theta, scale, tx, ty, seed, k):
    src = np.random.default_rng(seed).uniform(-10.0, 10.0, (k, 2))
    if np.linalg.matrix_rank(src - src.mean(axis=0), tol=1e-3) < 2:
        return
    truth = Similarity2D(theta, np.array([tx, ty]), scale)
    dst = truth.apply(src)
    est = umeyama_2d(src, dst)
    dth = (est.theta_rad - theta + np.pi) % (2 * np.pi) - np.pi
    assert abs(dth) < 1e-7
    assert est.scale == pytest.approx(scale, rel=1e-7)
    np.testing.assert_allclose(est.translation, [tx, ty], atol=1e-6 * (1 + abs(tx) + abs(ty)))
    assert np.linalg.det(est.rotation) == pytest.approx(1.0)
    # the batched closed form agrees
    th_b, s_b, t_b = similarity_batch(src[None], dst[None])
    assert abs((th_b[0] - theta + np.pi) % (2 * np.pi) - np.pi) < 1e-7
    assert s_b[0] == pytest.approx(scale, rel=1e-7)
    np.testing.assert_allclose(t_b[0], [tx, ty], atol=1e-6 * (1 + abs(tx) + abs(ty)))


def test_mirror_images_get_no_reflection():
    rng = np.random.default_rng(1)
    src = rng.uniform(-5, 5, (12, 2))
    dst = src * np.array([-1.0, 1.0])  # a reflection: no proper rotation maps src onto it
    est = umeyama_2d(src, dst)
    assert np.linalg.det(est.rotation) == pytest.approx(1.0)
    assert np.sqrt(np.mean(np.sum((est.apply(src) - dst) ** 2, axis=1))) > 1.0


def test_rigid_fit_keeps_unit_scale():
    rng = np.random.default_rng(2)
    src = rng.uniform(-5, 5, (10, 2))
    dst = Similarity2D(0.3, np.array([1.0, 2.0]), 1.0).apply(src) + rng.normal(0, 0.01, (10, 2))
    est = umeyama_2d(src, dst, with_scale=False)
    assert est.scale == 1.0
    assert est.theta_rad == pytest.approx(0.3, abs=0.01)


def test_similarity_covariance_matches_monte_carlo():
    rng = np.random.default_rng(4)
    src = rng.uniform(-6, 6, (25, 2))
    truth = Similarity2D(0.7, np.array([100.0, -50.0]), 1.0)
    sigma = 0.1
    est = []
    covs = []
    for _ in range(400):
        dst = truth.apply(src) + rng.normal(0, sigma, src.shape)
        e = umeyama_2d(src, dst, with_scale=False)
        est.append([*e.translation, e.theta_rad])
        covs.append(similarity_covariance(e, src, dst, with_scale=False)[:3, :3])
    emp = np.cov(np.array(est).T)
    pred = np.mean(covs, axis=0)
    np.testing.assert_allclose(np.sqrt(np.diag(pred)), np.sqrt(np.diag(emp)), rtol=0.15)


def test_binomial_tail_matches_scipy():
    for n, p, k in [(37, 0.2, 20), (80, 0.05, 3), (40, 0.01, 25), (10, 0.5, 0), (10, 0.5, 11)]:
        ref = binom.sf(k - 1, n, p)
        got = log10_binomial_tail(k, n, p)
        if ref == 0:
            assert got == -math.inf or got < -300
        else:
            assert got == pytest.approx(math.log10(ref), abs=1e-6)


def test_chance_probability_of_a_poisson_field():
    rng = np.random.default_rng(5)
    field = rng.uniform(0, 200, (12000, 2))  # 0.3 rocks / m^2
    tree = cKDTree(field)
    probe = rng.uniform(20, 180, (20000, 2))
    hit = np.mean(tree.query(probe, distance_upper_bound=0.5)[0] <= 0.5)
    assert hit == pytest.approx(chance_probability(0.3, 0.5), abs=0.01)


def test_inliers_are_one_to_one():
    cat = np.array([[0.0, 0.0], [10.0, 0.0]])
    pts = np.array([[0.05, 0.0], [0.02, 0.0], [10.3, 0.0], [5.0, 5.0]])
    inl = score_points(cKDTree(cat), pts, 0.2)
    assert inl.local_idx.tolist() == [1]  # the closer of two claims on rock 0; rock 1 too far
    assert inl.catalog_idx.tolist() == [0]
    assert rotation_2d(0.0).tolist() == [[1.0, 0.0], [0.0, 1.0]]


def test_inliers_pair_with_the_nearest_size_compatible_rock():
    cat = np.array([[0.0, 0.0], [0.3, 0.0], [5.0, 0.0]])
    cat_ls = np.log(np.array([1.0, 0.3, 0.3]))
    pts = np.array([[0.1, 0.0], [5.0, 0.1]])
    loc_ls = np.log(np.array([0.3, 1.0]))
    inl = score_points(cKDTree(cat), pts, 0.4, (loc_ls, cat_ls, np.log(1.6)))
    # rock 0 is nearer but three times larger: the local rock pairs with rock 1; the second
    # local rock has no compatible rock within the radius
    assert inl.local_idx.tolist() == [0] and inl.catalog_idx.tolist() == [1]
    assert inl.dist_m[0] == pytest.approx(0.2)
    # without sizes the nearest rock wins
    assert score_points(cKDTree(cat), pts, 0.4).catalog_idx.tolist() == [0, 2]


def _umeyama_svd(src, dst, w, with_scale):
    """Reference: the SVD form with the reflection fix (Umeyama 1991)."""
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    s0, d0 = src - mu_s, dst - mu_d
    u, sv, vt = np.linalg.svd((d0 * w[:, None]).T @ s0)
    fix = np.diag([1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    rot = u @ fix @ vt
    var = np.sum(w * np.sum(s0 * s0, axis=1))
    scale = float(np.trace(np.diag(sv) @ fix) / var) if with_scale else 1.0
    return np.arctan2(rot[1, 0], rot[0, 0]), mu_d - scale * rot @ mu_s, scale


@settings(max_examples=100, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    k=st.integers(2, 30),
    with_scale=st.booleans(),
    mirrored=st.booleans(),
)
def test_closed_form_fit_equals_the_svd_fit(seed, k, with_scale, mirrored):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-10, 10, (k, 2))
    rot = rotation_2d(rng.uniform(-np.pi, np.pi))
    dst = src @ rot.T * rng.uniform(0.5, 2) + rng.normal(0, 1.0, (k, 2))
    if mirrored:  # the best proper rotation of a mirror image
        dst[:, 0] *= -1
    w = rng.uniform(0.1, 1.0, k)
    theta, t, scale = _umeyama_svd(src, dst, w, with_scale)
    got = umeyama_2d(src, dst, w, with_scale=with_scale)
    # equal as transforms (the angle is ill-defined when the cross-covariance vanishes)
    ref = Similarity2D(theta, t, scale).apply(src)
    np.testing.assert_allclose(got.apply(src), ref, atol=1e-6 * (1 + np.abs(dst).max()))


def test_poisson_binomial_tail_is_exact_and_below_the_mean_binomial():
    rng = np.random.default_rng(3)
    for _ in range(20):
        n = int(rng.integers(1, 9))
        p = rng.uniform(0.0, 0.6, n)
        # brute force over all 2^n outcomes
        outcomes = np.array(np.meshgrid(*[[0, 1]] * n, indexing="ij")).reshape(n, -1).T
        prob = np.prod(np.where(outcomes == 1, p, 1.0 - p), axis=1)
        succ = outcomes.sum(axis=1)
        for k in range(n + 2):
            ref = prob[succ >= k].sum()
            got = log10_poisson_binomial_tail(k, p)
            assert got == (-math.inf if ref == 0 else pytest.approx(math.log10(ref), abs=1e-9))
    # equal chances: the binomial tail; unequal ones: never above the binomial at the mean chance
    assert log10_poisson_binomial_tail(21, np.full(28, 0.26)) == pytest.approx(log10_binomial_tail(21, 28, 0.26))
    p = np.r_[np.full(14, 0.4), np.full(14, 0.12)]
    assert log10_poisson_binomial_tail(21, p) < log10_binomial_tail(21, 28, float(p.mean()))
    # tiny tails do not underflow
    assert log10_poisson_binomial_tail(300, np.full(400, 0.01)) == pytest.approx(
        log10_binomial_tail(300, 400, 0.01), abs=1e-6
    )


def test_coarse_scorer_never_misses_an_exact_inlier():
    rng = np.random.default_rng(4)
    cat = rng.uniform(0, 60, (1000, 2))
    cat_ls = rng.normal(np.log(0.3), 0.5, 1000)
    tol = math.log(1.6)
    scorer = CoarseScorer(cat, cat_ls, 0.5, tol)
    loc = rng.uniform(-8, 8, (30, 2))
    loc_ls = rng.normal(np.log(0.3), 0.5, 30)
    theta = rng.uniform(-np.pi, np.pi, 300)
    trans = rng.uniform(5, 55, (300, 2))
    got = scorer.score(theta, np.ones(300), trans, loc, scorer.masks(loc_ls, 30))
    tree = cKDTree(cat)
    exact = np.zeros(300, int)
    for j in range(300):
        w = Similarity2D(float(theta[j]), trans[j], 1.0).apply(loc)
        near = tree.query_ball_point(w, 0.5)
        exact[j] = sum(any(abs(cat_ls[c] - loc_ls[i]) <= tol for c in near[i]) for i in range(30))
    assert np.all(got >= exact)
    assert np.mean(got) < 2.0 * np.mean(exact) + 1.0  # a superset, but not a loose one
    # the true pose of rocks cut from the catalog scores every rock
    idx = rng.choice(1000, 30, replace=False)
    sim = Similarity2D(0.7, np.array([3.0, -2.0]), 1.0)
    rot = rotation_2d(0.7)
    local = (cat[idx] - sim.translation) @ rot  # R^T (w - t)
    full = scorer.score(np.array([0.7]), np.ones(1), sim.translation[None], local, scorer.masks(cat_ls[idx], 30))
    assert full[0] == 30
