"""Two mapped rocks identified together fix the rover where one alone cannot: each in its own
gate (which holds the rover's drift), and the pair of catalog entries reproducing the rocks'
separation within a gate the drift does not widen. The fix recovers position and heading within
its covariance; maps of no place in the catalog and ambiguous pairs give none."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.match_to_fix import fix_from_pair, identify_pair
from fgslam.relocalizer import Relocalizer
from fgslam.relocalizer_config import RelocalizerConfig
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.measurements import RockCatalog

ROCKS = np.array([[3.0, 2.0], [6.5, 4.0]])  # the two catalogued rocks the rover maps (4 m apart)
ROVER = np.array([1.0, 0.0])
YAW = 0.4
DRIFT_XY, DRIFT_YAW = np.array([0.35, -0.25]), 0.03  # the estimate's error: a rotation about the rover, then a shift
ROVER_SIGMA, OWN_SIGMA = 0.4, 0.03


def _rot(a: float) -> np.ndarray:
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def _to_estimate(xy: np.ndarray) -> np.ndarray:
    return (xy - ROVER) @ _rot(DRIFT_YAW).T + ROVER + DRIFT_XY


def _catalog(n: int = 40, half_m: float = 25.0, extra=()) -> RockCatalog:
    """ERC MY2021's density or so: n rocks over a (2 half_m)^2 yard, the two mapped ones among them."""
    rng = np.random.default_rng(2)
    others = rng.uniform(-half_m, half_m, (4 * n, 2))
    others = others[np.min(np.linalg.norm(others[:, None] - ROCKS[None], axis=2), axis=1) > 3.0][: n - 2]
    xy = np.vstack([ROCKS, others, np.reshape(extra, (-1, 2))])
    return RockCatalog(xy, np.full(len(xy), 0.6), np.ones(len(xy)))


def _scene(xy_true: np.ndarray = ROCKS):
    T = np.eye(4)
    T[:2, 3] = _to_estimate(ROVER)
    T[:2, :2] = _rot(YAW + DRIFT_YAW)
    est = PoseEstimate(100.0, T, np.diag([ROVER_SIGMA**2, ROVER_SIGMA**2, 0.01, 1e-4, 1e-4, DRIFT_YAW**2]))
    n = len(xy_true)
    cov = np.tile(np.eye(3) * OWN_SIGMA**2, (n, 1, 1))
    cov[:, :2, :2] += est.cov[:2, :2]  # mapped from the rover's poses: its drift shared
    lmap = LandmarkMap(np.arange(n), np.column_stack([_to_estimate(np.asarray(xy_true)), np.zeros(n)]), cov,
                       np.full(n, 0.6), np.full(n, 5), "rocks")
    return est, lmap


def _cfg(**kw) -> RelocalizerConfig:
    return RelocalizerConfig(min_new_observations=0, min_travel_m=0.0, min_turn_deg=0.0, **kw)


def test_two_rocks_fix_position_and_heading_where_one_alone_cannot():
    est, lmap = _scene()
    cat = _catalog()
    alone = Relocalizer(cat, _cfg(pair_landmarks=False)).attempt({"rocks": lmap}, est)
    assert alone.status == "too few landmarks"  # one rock's gate holds 0.4 m of drift: too likely by chance
    att = Relocalizer(cat, _cfg()).attempt({"rocks": lmap}, est)
    assert att.status == "fix" and att.single and att.fix.n_inliers == 2
    assert att.fix.catalog_rows == (0, 1)
    assert np.allclose([att.fix.x_m, att.fix.y_m], ROVER, atol=1e-9)  # the drift undone exactly
    assert att.fix.yaw_rad == pytest.approx(YAW, abs=1e-9)
    assert 0.0 < att.false_alarm <= 1e-3
    # the heading from a 4 m baseline: both ends' catalog sigma and floor across it, inflated
    sigma_m = 0.1  # the matcher's default
    expect = 1.75 * np.sqrt(2 * (sigma_m**2 + 0.05**2)) / np.linalg.norm(ROCKS[1] - ROCKS[0])
    assert np.sqrt(att.fix.cov_xyyaw[2, 2]) == pytest.approx(expect, rel=0.05)


def test_the_pair_fix_covariance_holds_its_errors():
    """Catalog entries off by their sigma and rocks off the rover by their own: the fix's errors
    over 400 draws have a mean NEES of 3 (x, y, yaw) once the inflation is taken out."""
    rng = np.random.default_rng(11)
    est, _ = _scene()
    cfg = _cfg()
    sigma_m, rel_sigma = 0.1, 0.05  # rel at the floor: the drift is shared
    rel = np.tile(np.eye(2) * rel_sigma**2, (2, 1, 1))
    nees = []
    for _ in range(400):
        L = _to_estimate(ROCKS) + rng.normal(0.0, rel_sigma, (2, 2))
        C = ROCKS + rng.normal(0.0, sigma_m, (2, 2))
        fix = fix_from_pair(est, L, rel, C, cfg, sigma_m, t_recv=est.t)
        e = np.array([fix.x_m - ROVER[0], fix.y_m - ROVER[1], np.angle(np.exp(1j * (fix.yaw_rad - YAW)))])
        nees.append(e @ np.linalg.solve(fix.cov_xyyaw / cfg.inflation**2, e))
    assert 2.6 < np.mean(nees) < 3.4


def test_maps_of_no_place_in_the_catalog_give_no_pair_fix():
    """Two to six rocks mapped where the catalog has none of them (its density, the rover's 0.4 m
    drift): 300 attempts, no pair passes the bound (1e-3 per attempt); without the bound, chance
    entries fit both gates of some pairs."""
    rng = np.random.default_rng(4)
    cat = _catalog()
    cfg = _cfg()
    from scipy.spatial import cKDTree

    tree = cKDTree(cat.xy_m)
    est, _ = _scene()
    unbounded = _cfg(single_max_false_alarm=0.999)
    passed = fooled = 0
    for _ in range(300):
        n = int(rng.integers(2, 7))
        xy = ROVER + rng.uniform(-8.0, 8.0, (n, 2))
        _, lmap = _scene(xy)
        args = (lmap, np.arange(n), est.position_m, cat.xy_m, cat.size_m, tree)
        passed += identify_pair(*args, cfg, 0.1, 3.0) is not None
        fooled += identify_pair(*args, unbounded, 0.1, 3.0) is not None
    assert passed == 0 and fooled >= 3


def test_an_ambiguous_pair_gives_no_fix_and_a_lost_rover_a_weak_right_one():
    est, lmap = _scene()
    # a second entry beside the far rock that reproduces the separation as well: which one is it?
    cat = _catalog(extra=[ROCKS[1] + [0.12, 0.0]])
    att = Relocalizer(cat, _cfg()).attempt({"rocks": lmap}, est)
    assert att.status == "too few landmarks"
    # lost (20 m) since the rocks were mapped: their gates and separation identify them as before,
    # and the fix claims the rover's drift relative to them
    lost = PoseEstimate(est.t, est.T_world_base, np.diag([400.0, 400.0, 0.01, 1e-4, 1e-4, 0.1]))
    assert lost.planar_sigma_m > RelocalizerConfig().lost_sigma_m
    att = Relocalizer(_catalog(), _cfg()).attempt({"rocks": lmap}, lost)
    assert att.status == "fix" and att.false_alarm <= 1e-3
    assert np.allclose(att.fix.xyyaw, [*ROVER, YAW], atol=1e-9)
    assert np.all(np.sqrt(np.diag(att.fix.cov_xyyaw)[:2]) > 19.0)


def test_a_dense_field_refuses_the_pair():
    """A kilometre world's rock field (an entry every ~4 m^2): chance pairs are too likely."""
    est, lmap = _scene()
    cat = _catalog(n=2500, half_m=50.0)
    assert Relocalizer(cat, _cfg()).attempt({"rocks": lmap}, est).status == "too few landmarks"


def test_the_pair_fix_takes_each_entrys_own_sigma():
    """A small and a big crater: entries off by their own sigma each (0.3 m and 0.9 m per axis,
    ``catalog_sigma`` of 3 m and 14 m craters at 0.06 D). Given one sigma each, the fix's mean
    NEES over 400 draws is 3; given the small one's for both, the fix claims too little."""
    from fgslam.match_to_fix import catalog_sigma

    rng = np.random.default_rng(12)
    est, _ = _scene()
    cfg = _cfg(catalog_sigma_rel=0.06)
    sig = catalog_sigma(cfg, 0.3, np.array([3.0, 14.0]))
    assert sig == pytest.approx([np.hypot(0.3, 0.18), np.hypot(0.3, 0.84)])
    rel = np.tile(np.eye(2) * 0.05**2, (2, 1, 1))

    def mean_nees(sigma_m) -> float:
        nees = []
        for _ in range(400):
            L = _to_estimate(ROCKS) + rng.normal(0.0, 0.05, (2, 2))
            C = ROCKS + rng.normal(0.0, 1.0, (2, 2)) * sig[:, None]
            fix = fix_from_pair(est, L, rel, C, cfg, sigma_m, t_recv=est.t)
            e = np.array([fix.x_m - ROVER[0], fix.y_m - ROVER[1], np.angle(np.exp(1j * (fix.yaw_rad - YAW)))])
            nees.append(e @ np.linalg.solve(fix.cov_xyyaw / cfg.inflation**2, e))
        return float(np.mean(nees))

    assert 2.6 < mean_nees(sig) < 3.4
    assert mean_nees(float(sig[0])) > 5.0


def test_a_pair_beyond_one_landmarks_radius_is_looked_for_within_pair_radius():
    """``pair_radius_m``: with a single radius of 2 m (the rocks lie 2.8 m and 6.8 m from the
    rover) no pair is looked for by default; within a pair radius of 10 m the pair gives the
    fix it gives at the default radius."""
    est, lmap = _scene()
    cat = _catalog()
    near = Relocalizer(cat, _cfg(single_radius_m=2.0)).attempt({"rocks": lmap}, est)
    assert near.status == "too few landmarks"
    far = Relocalizer(cat, _cfg(single_radius_m=2.0, pair_radius_m=10.0)).attempt({"rocks": lmap}, est)
    usual = Relocalizer(cat, _cfg()).attempt({"rocks": lmap}, est)
    assert far.status == usual.status == "fix" and far.fix.catalog_rows == (0, 1)
    assert far.fix.x_m == pytest.approx(usual.fix.x_m) and far.fix.y_m == pytest.approx(usual.fix.y_m)
    np.testing.assert_allclose(far.fix.cov_xyyaw, usual.fix.cov_xyyaw)
    with pytest.raises(Exception, match="pair_radius_m"):
        _cfg(pair_radius_m=0.0)


def test_a_far_pairs_fix_carries_its_lever_arm():
    """Two craters 20 m apart, 60 m from the rover: the pair's heading error moves the rover by
    60 m x that, and the fix's covariance says so (mean NEES 3 over 400 draws, inflation taken
    out), and its position sigma is the lever arm's metre and more."""
    rng = np.random.default_rng(13)
    est, _ = _scene()
    cfg = _cfg()
    pair = ROVER + np.array([[55.0, 20.0], [62.0, 38.8]])
    rel = np.tile(np.eye(2) * 0.1**2, (2, 1, 1))
    nees, pos_sigma = [], []
    for _ in range(400):
        L = _to_estimate(pair) + rng.normal(0.0, 0.1, (2, 2))
        C = pair + rng.normal(0.0, 0.3, (2, 2))
        fix = fix_from_pair(est, L, rel, C, cfg, 0.3, t_recv=est.t)
        e = np.array([fix.x_m - ROVER[0], fix.y_m - ROVER[1], np.angle(np.exp(1j * (fix.yaw_rad - YAW)))])
        cov = fix.cov_xyyaw / cfg.inflation**2
        nees.append(e @ np.linalg.solve(cov, e))
        pos_sigma.append(np.sqrt(np.trace(cov[:2, :2]) / 2))
    assert 2.6 < np.mean(nees) < 3.4
    # 60 m x the heading's sigma (sqrt(2 (0.1^2 + 0.3^2)) / 20 m = 0.022 rad) is ~1.3 m
    assert 1.0 < np.median(pos_sigma) < 2.0
