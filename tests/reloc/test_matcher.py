"""Seeded end-to-end matching on small synthetic catalogs; no-match answers; degenerate inputs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from reloc import Catalog, ConstellationMatcher, MatcherConfig, MatchResult
from reloc.catalog import CatalogError
from reloc.matcher import MatchInputError, MatchPrior

DENSITY = 0.3


def _field(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    side = np.sqrt(n / DENSITY)
    return rng.uniform(0, side, (n, 2)), rng.lognormal(np.log(0.3), 0.5, n)


def _query(xy, size, rng, sigma=0.05, n=40):
    """A 40-rock disc, 30 % dropped, 4 spurious, jittered, moved: (local_xy, local_size, theta, t, kept ids)."""
    side = np.ptp(xy[:, 0])
    center = rng.uniform(8.0, side - 8.0, 2)
    d = np.hypot(*(xy - center).T)
    idx = np.argsort(d)[:n]
    keep = idx[rng.random(n) >= 0.3]
    r = d[idx].max()
    ang, rr = rng.uniform(0, 2 * np.pi, 4), r * np.sqrt(rng.random(4))
    world = np.vstack([xy[keep] + rng.normal(0, sigma, (keep.size, 2)), center + np.c_[rr * np.cos(ang), rr * np.sin(ang)]])
    sizes = np.r_[size[keep] * np.exp(rng.normal(0, 0.15, keep.size)), rng.lognormal(np.log(0.3), 0.5, 4)]
    theta = rng.uniform(-np.pi, np.pi)
    t = center + rng.uniform(-30, 30, 2)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    return (world - t) @ rot, sizes, theta, t, keep


@pytest.fixture(scope="module")
def catalog():
    xy, size = _field(3000, 11)
    return Catalog(xy, size)


def _check(res: MatchResult, local, theta, t, pos_tol=0.3, head_tol_deg=2.0):
    c = local.mean(axis=0)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    err = np.hypot(*(res.apply(c[None])[0] - (rot @ c + t)))
    dth = abs((res.rotation_rad - theta + np.pi) % (2 * np.pi) - np.pi)
    assert err < pos_tol and np.degrees(dth) < head_tol_deg, (err, np.degrees(dth))


def test_recovers_seeded_queries(catalog):
    rng = np.random.default_rng(7)
    matcher = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05, seed=3))
    for _ in range(8):
        local, size, theta, t, keep = _query(catalog.xy, catalog.size, rng)
        res = matcher.match(local, size)
        assert res is not None
        _check(res, local, theta, t)
        # inliers pair local rocks with the catalog rocks they came from
        li, ci = res.inlier_pairs.T
        real = li < keep.size
        assert np.mean(keep[li[real]] == ci[real]) > 0.95
        assert res.n_inliers >= 15 and res.rmse_m < 0.15
        assert res.log10_false_alarm < -3 and abs(res.scale - 1.0) < 0.02
        cov = res.transform_cov
        assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)
        assert np.sqrt(cov[2, 2]) < np.radians(1.0)
        # the covariance at the centroid: position sigma about sigma / sqrt(K)
        cc = res.cov_at(local.mean(axis=0))
        assert 0.2 * 0.05 / np.sqrt(res.n_inliers) < np.sqrt(cc[0, 0]) < 5 * 0.05 / np.sqrt(res.n_inliers)


def test_recovers_noisier_queries(catalog):
    rng = np.random.default_rng(8)
    matcher = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.2))
    hits = 0
    for _ in range(5):
        local, size, theta, t, _ = _query(catalog.xy, catalog.size, rng, sigma=0.2)
        res = matcher.match(local, size)
        if res is not None:
            _check(res, local, theta, t, pos_tol=0.5, head_tol_deg=3.0)  # never a wrong fix
            hits += 1
    assert hits >= 4


def test_out_of_catalog_queries_get_no_match(catalog):
    other_xy, other_size = _field(3000, 99)
    rng = np.random.default_rng(9)
    matcher = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05))
    for _ in range(8):
        local, size, *_ = _query(other_xy, other_size, rng)
        assert matcher.match(local, size) is None


def test_mirrored_map_is_not_matched(catalog):
    rng = np.random.default_rng(10)
    matcher = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05))
    for _ in range(3):
        local, size, *_ = _query(catalog.xy, catalog.size, rng)
        assert matcher.match(local * np.array([-1.0, 1.0]), size) is None


def test_deterministic_for_a_seed(catalog):
    rng = np.random.default_rng(12)
    local, size, *_ = _query(catalog.xy, catalog.size, rng)
    cfg = MatcherConfig(sigma_m=0.05, seed=5)
    a = ConstellationMatcher(catalog, cfg).match(local, size)
    b = ConstellationMatcher(catalog, cfg).match(local, size)
    assert a is not None and b is not None
    assert a.rotation_rad == b.rotation_rad and np.array_equal(a.translation, b.translation)
    assert np.array_equal(a.inlier_pairs, b.inlier_pairs) and a.n_hypotheses == b.n_hypotheses


def test_prior_restricts_the_search(catalog):
    rng = np.random.default_rng(13)
    local, size, theta, t, _ = _query(catalog.xy, catalog.size, rng)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    center_w = rot @ local.mean(axis=0) + t
    matcher = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05))
    near = matcher.match(local, size, prior=MatchPrior(center_w + 1.0, 3.0))
    assert near is not None
    _check(near, local, theta, t)
    assert matcher.match(local, size, prior=MatchPrior(center_w + 40.0, 3.0)) is None


def test_works_without_sizes(catalog):
    rng = np.random.default_rng(14)
    local, _, theta, t, _ = _query(catalog.xy, catalog.size, rng)
    res = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05)).match(local, None)
    assert res is not None
    _check(res, local, theta, t)


def test_degenerate_local_maps_get_none_or_a_clear_error(catalog):
    m = ConstellationMatcher(catalog)
    assert m.match(np.zeros((0, 2)), np.zeros(0)) is None
    assert m.match(np.array([[0.0, 0.0], [1.0, 1.0]]), np.ones(2)) is None
    line = np.c_[np.linspace(0, 10, 20), np.linspace(0, 5, 20)]
    assert m.match(line, np.full(20, 0.3)) is None  # all collinear
    assert m.match(np.ones((10, 2)), np.full(10, 0.3)) is None  # all duplicates
    with pytest.raises(MatchInputError, match="NaN"):
        m.match(np.array([[0.0, 0.0], [np.nan, 1.0], [2.0, 0.0]]), np.ones(3))
    with pytest.raises(MatchInputError, match="shape"):
        m.match(np.zeros((5, 3)), np.ones(5))
    with pytest.raises(MatchInputError, match="local_size"):
        m.match(np.zeros((5, 2)), np.ones(4))
    with pytest.raises(MatchInputError, match="positive"):
        m.match(np.random.default_rng(0).uniform(0, 5, (5, 2)), -np.ones(5))


def test_bad_catalogs_raise():
    with pytest.raises(CatalogError, match="at least 3"):
        Catalog(np.zeros((2, 2)), np.ones(2))
    with pytest.raises(CatalogError, match="NaN"):
        Catalog(np.array([[0.0, 0.0], [1.0, np.nan], [2.0, 0.0]]), np.ones(3))
    with pytest.raises(CatalogError, match="positive"):
        Catalog(np.random.default_rng(0).uniform(0, 5, (5, 2)), np.zeros(5))
    with pytest.raises(MatchInputError):
        MatcherConfig(sigma_m=-1.0)


def test_catalog_rows_are_in_hash_order(catalog):
    # the key of every row's sides is the hash key at the same position
    q = np.floor(catalog.tri_sides_m.astype(float) / catalog.hash.bin_m).astype(np.int64)
    keys = catalog.hash._keys(q, np.ones(q.shape[0]))
    hand = np.where(catalog.hash.keys == keys, 1, -1)
    assert np.array_equal(catalog.hash._keys(q, hand), catalog.hash.keys)
    # rows hold the sides of the triangles their vertices form, and the vertices' size codes
    rows = np.random.default_rng(0).choice(catalog.n_triangles, 200, replace=False)
    v = catalog.tri_vertices[rows]
    xy = catalog.xy
    sides = np.sort(np.stack([np.hypot(*(xy[v[:, i]] - xy[v[:, j]]).T) for i, j in ((1, 2), (0, 2), (0, 1))], 1), 1)
    assert np.allclose(sides, catalog.tri_sides_m[rows], atol=1e-3)
    code = np.round((catalog.log_size[v] - catalog.size_q_lo) / catalog.size_q_step)
    assert np.array_equal(code, catalog.tri_size_q[rows])
    # count() agrees with the candidates query() returns
    qs, qh = catalog.tri_sides_m[rows[:20]].astype(float), np.ones(20)
    qi, _ = catalog.hash.query(qs, qh, 0.2)
    assert np.array_equal(catalog.hash.count(qs, qh, 0.2), np.bincount(qi, minlength=20))


def test_catalog_index_is_compact(catalog):
    assert catalog.tri_vertices.dtype == np.int32 and catalog.tri_sides_m.dtype == np.float32
    assert catalog.n_triangles > 5 * len(catalog)
    assert catalog.nbytes < 64 * catalog.n_triangles
    assert dataclasses.is_dataclass(catalog.config)


def test_false_alarm_bound_pays_for_hypotheses_and_verifications(catalog):
    from reloc.scoring import log10_binomial_tail

    rng = np.random.default_rng(15)
    matcher = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.1))
    for _ in range(4):
        local, size, *_ = _query(catalog.xy, catalog.size, rng, sigma=0.1)
        res = matcher.match(local, size)
        assert res is not None
        m = local.shape[0]
        tail = log10_binomial_tail(res.n_inliers - 3, m - 3, res.chance_probability)
        # every generated hypothesis and every verification (at least one pose each) is a test,
        # and a stage weight is at most 1
        assert res.log10_false_alarm >= tail + np.log10(res.n_hypotheses + res.n_verified) - 1e-9


def test_returned_pose_is_settled_on_its_inliers(catalog):
    from reloc.procrustes import umeyama_2d
    from reloc.scoring import score_points

    rng = np.random.default_rng(16)
    cfg = MatcherConfig(sigma_m=0.2)
    matcher = ConstellationMatcher(catalog, cfg)
    for _ in range(4):
        local, size, *_ = _query(catalog.xy, catalog.size, rng, sigma=0.2)
        res = matcher.match(local, size)
        if res is None:
            continue
        li, ci = res.inlier_pairs.T
        refit = umeyama_2d(local[li], catalog.xy[ci], with_scale=False)
        chk = (np.log(size).astype(np.float32), catalog.log_size, np.log(cfg.size_ratio_max))
        again = score_points(catalog.tree, refit.apply(local), cfg.inlier_radius_m, chk)
        assert (again.count, -again.rmse_m) <= (res.n_inliers, -res.rmse_m + 1e-12)


def test_triangle_order_is_a_seeded_permutation_of_distinctive_triangles_first(catalog):
    rng = np.random.default_rng(17)
    local, size, *_ = _query(catalog.xy, catalog.size, rng)
    ls = np.log(size).astype(np.float32)
    plain = ConstellationMatcher(catalog, MatcherConfig(seed=4, fewest_candidates_first=False))
    ranked = ConstellationMatcher(catalog, MatcherConfig(seed=4))
    tri = ranked._local_triangles(local)
    a, b = plain._triangle_order(local, tri, ls), ranked._triangle_order(local, tri, ls)
    assert np.array_equal(a, np.random.default_rng(4).permutation(len(tri)))
    assert np.array_equal(np.sort(b), np.arange(len(tri)))
    # the first triangles have fewer catalog look-alikes than the last ones
    cfg = ranked.config
    tol = cfg.side_tol_m + cfg.scale_tol * tri.sides_m[:, 2]
    n = catalog.hash.count(tri.sides_m, tri.handedness, tol)
    q = len(tri) // 4
    assert np.mean(n[b[:q]]) < np.mean(n[b[-q:]])


def test_wider_second_pass_is_optional_and_only_adds_hypotheses(catalog):
    rng = np.random.default_rng(18)
    other_xy, other_size = _field(3000, 98)
    local, size, *_ = _query(other_xy, other_size, rng)  # not in the catalog: the search runs out
    one = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05, wide_side_tol_sigmas=None))
    two = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05, wide_max_hypotheses=10**9))
    assert one.match(local, size) is None and two.match(local, size) is None
    local, size, theta, t, _ = _query(catalog.xy, catalog.size, rng)
    res = one.match(local, size)
    assert res is not None
    _check(res, local, theta, t)


def test_stage_weights_sum_to_at_most_one():
    from reloc.matcher import _stage_weights

    for passes in ([1], [5], [3, 4], [1, 1], [6, 2]):
        w = _stage_weights(passes)
        assert len(w) == sum(passes) and all(x > 0 for x in w) and sum(w) <= 1.0 + 1e-12
    w = _stage_weights([5])
    assert w[:4] == [0.25, 0.125, 0.0625, 0.03125] and w[-1] >= 0.5  # one pass: as before


def _truth_sim(theta, t):
    from reloc.procrustes import Similarity2D

    return Similarity2D(float(theta), np.asarray(t, float), 1.0)


def test_a_good_guess_is_verified_without_a_search(catalog):
    from reloc.procrustes import Similarity2D
    from reloc.scoring import log10_binomial_tail

    rng = np.random.default_rng(19)
    cfg = MatcherConfig(sigma_m=0.05)
    matcher = ConstellationMatcher(catalog, cfg)
    for _ in range(4):
        local, size, theta, t, _ = _query(catalog.xy, catalog.size, rng)
        searched = matcher.match(local, size)
        truth = _truth_sim(theta, t)
        center_w = truth.apply(local.mean(axis=0)[None])[0]
        # the guess is off by 0.15 m and 0.3 deg, as a localized rover's estimate would be
        guess = Similarity2D(theta + np.radians(0.3), t + np.array([0.1, -0.11]), 1.0)
        res = matcher.match(local, size, prior=MatchPrior(center_w, 3.0, guess))
        assert res is not None and res.from_guess and not searched.from_guess
        assert res.n_hypotheses == 1 and res.n_verified == 1
        _check(res, local, theta, t, pos_tol=0.05, head_tol_deg=0.3)
        assert res.n_inliers >= searched.n_inliers - 2
        # the guess's test: its share of the budget, the poses its re-fits can reach (at most
        # (2 first_stage_factor)^3), every inlier as evidence (none of them built the guess)
        tail = log10_binomial_tail(res.n_inliers, local.shape[0], res.chance_probability)
        assert res.log10_false_alarm >= tail + np.log10(2.0) - np.log10(cfg.guess_share) - 1e-9
        reach = (2.0 * cfg.first_stage_factor) ** 3
        assert res.log10_false_alarm <= tail + np.log10(1.0 + reach) - np.log10(cfg.guess_share) + 1e-9


def test_a_wrong_guess_falls_back_to_the_search(catalog):
    from reloc.procrustes import Similarity2D

    rng = np.random.default_rng(20)
    matcher = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05))
    local, size, theta, t, _ = _query(catalog.xy, catalog.size, rng)
    center_w = _truth_sim(theta, t).apply(local.mean(axis=0)[None])[0]
    # 2 m and 20 deg off: nothing near it, the triangle search (inside the prior) finds the pose
    wrong = Similarity2D(theta + np.radians(20.0), t + np.array([2.0, 0.0]), 1.0)
    res = matcher.match(local, size, prior=MatchPrior(center_w, 4.0, wrong))
    assert res is not None and not res.from_guess and res.n_hypotheses > 1
    _check(res, local, theta, t)
    # a map that is not in the catalog is not matched, with or without a guess
    other_xy, other_size = _field(3000, 97)
    local, size, *_ = _query(other_xy, other_size, rng)
    guess = Similarity2D(0.0, np.zeros(2), 1.0)
    assert matcher.match(local, size, prior=MatchPrior(local.mean(axis=0), 4.0, guess)) is None


def test_guess_share_and_bad_priors_are_checked(catalog):
    from reloc.procrustes import Similarity2D

    with pytest.raises(MatchInputError, match="guess_share"):
        MatcherConfig(guess_share=1.0)
    matcher = ConstellationMatcher(catalog, MatcherConfig(sigma_m=0.05))
    local, size, *_ = _query(catalog.xy, catalog.size, np.random.default_rng(21))
    c = local.mean(axis=0)
    for prior, what in (
        (MatchPrior(np.array([np.nan, 0.0]), 3.0), "center_xy"),
        (MatchPrior(c, -1.0), "radius_m"),
        (MatchPrior(c, 3.0, Similarity2D(np.nan, np.zeros(2), 1.0)), "guess"),
        (MatchPrior(c, 3.0, Similarity2D(0.0, np.zeros(2), 0.0)), "guess"),
    ):
        with pytest.raises(MatchInputError, match=what):
            matcher.match(local, size, prior=prior)
