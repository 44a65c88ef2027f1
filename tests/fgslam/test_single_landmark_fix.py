"""A crater identified alone with its catalog entry fixes the rover's position where too few
craters are mapped to match: the fix moves the rover by what puts the crater on its entry, its
covariance is the catalog's sigma plus the crater's error relative to the rover, and ambiguous,
crowded or lost cases give no fix."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.crater_relocalizer import CraterRelocalizer
from fgslam.relocalizer import RelocalizerError
from fgslam.relocalizer_config import RelocalizerConfig
from reloc.backend import LandmarkMap, PoseEstimate
from reloc.measurements import RockCatalog

# the rover's estimate has drifted by DRIFT: the crater it maps sits DRIFT off its catalog entry
DRIFT = np.array([1.2, -0.8])
CRATER = np.array([110.0, 48.0])


def _est(sigma_m: float, t: float = 100.0) -> PoseEstimate:
    T = np.eye(4)
    T[:2, 3] = CRATER - np.array([12.0, 3.0]) + DRIFT  # 12 m behind the crater, as it believes
    T[:2, :2] = [[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]
    cov = np.diag([sigma_m**2, sigma_m**2, 0.01, 1e-4, 1e-4, 1e-5])
    return PoseEstimate(t, T, cov)


def _map(est: PoseEstimate, rel_sigma_m: float = 0.15) -> LandmarkMap:
    """One crater of 3 m, mapped DRIFT off its truth, its world covariance the rover's plus its own."""
    cov = np.eye(3) * rel_sigma_m**2
    cov[:2, :2] += est.cov[:2, :2]
    return LandmarkMap(np.array([7]), np.array([[*(CRATER + DRIFT), 0.0]]), cov[None], np.array([3.0]),
                       np.array([6]), "craters")


def _catalog(extra_xy=(), extra_size=()) -> RockCatalog:
    rng = np.random.default_rng(5)
    far = rng.uniform(-400, 400, (40, 2))
    far = far[np.linalg.norm(far - CRATER, axis=1) > 150]  # young ground: craters ~100 m apart or more
    xy = np.vstack([CRATER, far, np.reshape(extra_xy, (-1, 2))])
    size = np.concatenate([[3.1], rng.uniform(1.0, 6.0, len(far)), np.asarray(extra_size, float)])
    return RockCatalog(xy, size, np.ones(len(xy)))


def _reloc(cat: RockCatalog, **kw) -> CraterRelocalizer:
    return CraterRelocalizer(cat, {"min_new_observations": 0, "min_travel_m": 0.0, "min_turn_deg": 0.0, **kw})


def test_one_identified_crater_fixes_the_position_within_its_covariance():
    est = _est(0.5)
    att = _reloc(_catalog()).attempt({"craters": _map(est)}, est)
    assert att.status == "fix" and att.single and att.fix.n_inliers == 1
    err = np.array([att.fix.x_m, att.fix.y_m]) - (est.position_m[:2] - DRIFT)
    assert np.linalg.norm(err) < 1e-9  # exact: the map's only error was the drift
    assert att.fix.yaw_rad == pytest.approx(est.yaw_rad)
    cov = att.fix.cov_xyyaw
    # the catalog's 0.3 m per axis and 0.06 of the entry's 3.1 m in quadrature, plus the crater's
    # 0.15 m relative to the rover (not the 0.5 m drift), inflated as a matched fix is (1.75)
    assert np.allclose(cov[:2, :2], 1.75**2 * (0.3**2 + (0.06 * 3.1) ** 2 + 0.15**2) * np.eye(2), atol=1e-9)
    assert np.sqrt(cov[2, 2]) == pytest.approx(0.5)  # no heading information
    assert 0 < att.false_alarm <= 1e-3
    assert np.allclose(att.world_xy, [CRATER]) and np.allclose(att.local_xy, [CRATER + DRIFT])


@pytest.mark.parametrize("diameter_m", [3.0, 12.0])
def test_a_big_craters_fix_claims_its_catalog_centre_error(diameter_m):
    """Catalog centres drawn off by 0.3 m (half a pixel, the rim fits) and 0.06 D (the orbital
    detector's error) per axis: over 300 draws the single fixes' mean NEES (x, y; inflation taken
    out) is 2 for a 3 m and a 12 m crater alike. With the matcher's 0.3 m for every size
    (``catalog_sigma_rel: 0``) the 12 m crater's fixes claim a third of their error."""
    rng = np.random.default_rng(21)
    est = _est(1.0)  # a drift of 1.4 m: the gate holds it and the entry's error
    lmap = _map(est, rel_sigma_m=0.05)
    lmap = LandmarkMap(lmap.ids, lmap.xyz_world_m, lmap.cov_world_m2, np.array([diameter_m]), lmap.n_obs, "craters")
    truth = est.position_m[:2] - DRIFT

    def mean_nees(**kw) -> float:
        nees = []
        for _ in range(300):
            cat = _catalog()
            xy = cat.xy_m.copy()
            xy[0] = CRATER + rng.normal(0.0, np.hypot(0.3, 0.06 * diameter_m), 2)
            size = cat.size_m.copy()
            size[0] = diameter_m
            att = _reloc(RockCatalog(xy, size, cat.score), single_max_false_alarm=0.5, **kw).attempt({"craters": lmap}, est)
            assert att.status == "fix" and att.fix.catalog_rows == (0,)
            e = np.array([att.fix.x_m, att.fix.y_m]) - truth
            nees.append(e @ np.linalg.solve(att.fix.cov_xyyaw[:2, :2] / 1.75**2, e))
        return float(np.mean(nees))

    assert 1.6 < mean_nees() < 2.4
    if diameter_m > 10:
        assert mean_nees(catalog_sigma_rel=0.0) > 5.0


def test_a_second_use_of_the_same_crater_is_deweighted():
    est = _est(0.5)
    reloc = _reloc(_catalog())
    a, b = (reloc.attempt({"craters": _map(est)}, est) for _ in range(2))
    assert np.allclose(b.fix.cov_xyyaw, 2.0 * a.fix.cov_xyyaw)  # correlation "rocks": 1 + earlier uses


def test_ambiguous_crowded_far_or_lost_gives_no_fix():
    est = _est(0.5)
    near = CRATER + np.array([1.0, 0.0])  # a second entry of the same size inside the gate
    assert _reloc(_catalog([near], [2.9])).attempt({"craters": _map(est)}, est).status == "too few landmarks"
    # of another size it is not a candidate
    assert _reloc(_catalog([near], [9.0])).attempt({"craters": _map(est)}, est).status == "fix"
    # ... unless the matcher checks no size: then it is a candidate, and the pair is ambiguous
    no_size = _reloc(_catalog([near], [9.0]), matcher={"size_ratio_max": None})
    assert no_size.attempt({"craters": _map(est)}, est).status == "too few landmarks"
    # a crowded neighbourhood: a chance entry in the gate is too likely
    ring = CRATER + 30.0 * np.column_stack([np.cos(np.arange(60)), np.sin(np.arange(60))]) * np.linspace(0.3, 1, 60)[:, None]
    att = _reloc(_catalog(ring, np.full(60, 3.0))).attempt({"craters": _map(est)}, est)
    assert att.status == "too few landmarks"
    # the drift beyond the gate: no candidate
    wide = _est(0.1)
    assert _reloc(_catalog()).attempt({"craters": _map(wide)}, wide).status == "too few landmarks"
    # a crater beyond single_radius_m
    assert _reloc(_catalog(), single_radius_m=5.0).attempt({"craters": _map(est)}, est).status == "too few landmarks"
    # a lost rover (6 m): its crater's gate holds the drift, and a chance entry in it is too likely
    lost = _est(6.0)
    assert _reloc(_catalog()).attempt({"craters": _map(lost)}, lost).status == "too few landmarks"
    # off
    assert _reloc(_catalog(), single_landmark=False).attempt({"craters": _map(est)}, est).status == "too few landmarks"


def test_a_lost_rover_is_identified_as_its_bound_allows_never_beyond_the_density_disc():
    """Lost (a planar sigma above ``lost_sigma_m``) is no reason of its own: the crater's gate
    holds the rover's drift and the bound counts the chance entries in it. With a bound that
    allows a gate of 6 m sigma, the crater is identified and the fix is right, claiming the
    catalog's error and the crater's relative to the rover, not the drift; a gate reaching beyond
    ``single_density_radius_m`` (200 m, 60 m sigma), where the density counted does not describe
    it, identifies nothing at any bound."""
    lost = _est(6.0)
    assert lost.planar_sigma_m > RelocalizerConfig().lost_sigma_m
    att = _reloc(_catalog(), single_max_false_alarm=0.05).attempt({"craters": _map(lost)}, lost)
    assert att.status == "fix" and att.single and 1e-3 < att.false_alarm <= 0.05
    err = np.array([att.fix.x_m, att.fix.y_m]) - (lost.position_m[:2] - DRIFT)
    assert np.linalg.norm(err) < 1e-9
    assert np.allclose(att.fix.cov_xyyaw[:2, :2], 1.75**2 * (0.3**2 + (0.06 * 3.1) ** 2 + 0.15**2) * np.eye(2), atol=1e-9)
    very = _est(60.0)
    att = _reloc(_catalog(), single_max_false_alarm=0.5).attempt({"craters": _map(very)}, very)
    assert att.status == "too few landmarks"


def test_single_settings_are_checked():
    with pytest.raises(RelocalizerError, match="single_max_false_alarm"):
        RelocalizerConfig(single_max_false_alarm=0.0)
    with pytest.raises(RelocalizerError, match="single_gate_chi2"):
        RelocalizerConfig(single_gate_chi2=-1.0)
    assert RelocalizerConfig().single_landmark  # every kind: the bound decides


def _rock_scene(n_catalog: int, half_m: float, seed: int = 3, rover_sigma_m: float = 0.2,
                drift=(0.3, -0.2), rock_sigma_m: float = 0.1):
    """A rover ``drift`` off among 4 mapped rocks (``rock_sigma_m`` each, plus the rover's), one
    of them catalogued, in a yard of ``n_catalog`` catalogued rocks of 0.5-1.5 m over (2
    half_m)^2; the rover's planar sigma ``rover_sigma_m``."""
    rng = np.random.default_rng(seed)
    rock = np.array([4.0, 2.0])
    others = rng.uniform(-half_m, half_m, (n_catalog - 1, 2))
    others = others[np.linalg.norm(others - rock, axis=1) > 2.0]
    cat = RockCatalog(np.vstack([rock, others]), np.concatenate([[0.9], rng.uniform(0.5, 1.5, len(others))]),
                      np.ones(len(others) + 1))
    drift = np.asarray(drift, float)
    T = np.eye(4)
    T[:2, 3] = drift
    est = PoseEstimate(50.0, T, np.diag([rover_sigma_m**2, rover_sigma_m**2, 0.01, 1e-4, 1e-4, 1e-4]))
    # the catalogued rock and three the catalog missed, mapped through the drift
    xy = np.vstack([rock, [[-3.0, 5.0], [6.0, -4.0], [-5.0, -5.5]]]) + drift
    cov = np.tile(np.eye(3) * rock_sigma_m**2, (4, 1, 1))
    cov[:, :2, :2] += est.cov[:2, :2]
    lmap = LandmarkMap(np.arange(4), np.column_stack([xy, np.zeros(4)]), cov, np.array([0.9, 0.6, 0.7, 0.8]),
                       np.full(4, 5), "rocks")
    return cat, est, lmap, drift


def test_one_rock_of_a_sparse_catalog_fixes_the_position_by_default():
    """A yard sparser than ERC MY2021's (12 catalogued rocks over 47 x 47 m): too few mapped rocks
    are catalogued to match a constellation, and the one that is fixes the rover's position when
    the gate is tight (rover and rock known to 5 cm, 6 cm of drift). At ERC MY2021's density (23
    rocks) with the rover at 20 cm and 36 cm off, a chance entry in the gate is likelier than the
    bound (~0.01 per m^2 over the gate) and the rock gives no fix."""
    from fgslam.relocalizer import Relocalizer

    cfg = RelocalizerConfig(min_new_observations=0, min_travel_m=0.0, min_turn_deg=0.0)
    cat, est, lmap, drift = _rock_scene(12, 23.5, rover_sigma_m=0.05, drift=(0.05, -0.03), rock_sigma_m=0.05)
    att = Relocalizer(cat, cfg).attempt({"rocks": lmap}, est)
    assert att.status == "fix" and att.single and att.source == "rocks"
    assert np.allclose([att.fix.x_m, att.fix.y_m], est.position_m[:2] - drift, atol=1e-9)
    assert att.false_alarm <= cfg.single_max_false_alarm
    assert np.allclose(att.world_xy, [cat.xy_m[0]])
    cat, est, lmap, _ = _rock_scene(23, 23.5)
    att = Relocalizer(cat, cfg).attempt({"rocks": lmap}, est)
    assert att.status == "too few landmarks" and not att.single


def test_a_small_catalog_counts_its_density_over_its_own_extent():
    """The chance of an entry in the gate is the catalog's density where it has entries: a 30 x
    30 m catalog counted over the whole 200 m disc would look 140x sparser. Random local maps
    (nowhere in the catalog) of a rover sure to 1 cm never get a single-landmark fix; before, 4 of
    the first 12 seeds did."""
    from fgslam.relocalizer import Relocalizer

    fixes = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        sizes = rng.uniform(0.3, 1.5, 40)
        cat = RockCatalog(rng.uniform(-15, 15, (40, 2)), sizes, np.ones(40))
        reloc = Relocalizer(cat, RelocalizerConfig(min_new_observations=0, min_travel_m=0.0, min_turn_deg=0.0))
        xy = rng.uniform(-15, 15, (40, 2))
        lmap = LandmarkMap(np.arange(40), np.column_stack([xy, np.zeros(40)]), np.tile(np.eye(3) * 1e-4, (40, 1, 1)),
                           rng.permutation(sizes), np.full(40, 5), "rocks")
        att = reloc.attempt({"rocks": lmap}, PoseEstimate(0.0, np.eye(4), np.eye(6) * 1e-4))
        fixes += att.status == "fix"
    assert fixes == 0


def test_the_disc_inside_a_box():
    from fgslam.match_to_fix import disc_box_area

    assert disc_box_area((0.0, 0.0), 1.0, (-5.0, -5.0, 5.0, 5.0)) == pytest.approx(np.pi, rel=1e-3)
    assert disc_box_area((0.0, 0.0), 1.0, (0.0, 0.0, 5.0, 5.0)) == pytest.approx(np.pi / 4, rel=1e-3)
    assert disc_box_area((0.0, 0.0), 200.0, (-25.0, -25.0, 25.0, 25.0)) == pytest.approx(2500.0, rel=1e-3)
    assert disc_box_area((100.0, 0.0), 1.0, (-5.0, -5.0, 5.0, 5.0)) == 0.0


def test_one_rock_of_a_dense_catalog_is_not_identified_alone():
    """A kilometre world's rock field (a catalogued rock every ~4 m^2): a chance entry in the gate
    is too likely, so the bound refuses and the rock gives no fix."""
    from fgslam.relocalizer import Relocalizer

    cat, est, lmap, _ = _rock_scene(2500, 50.0)
    cfg = RelocalizerConfig(min_new_observations=0, min_travel_m=0.0, min_turn_deg=0.0)
    att = Relocalizer(cat, cfg).attempt({"rocks": lmap}, est)
    assert att.status == "too few landmarks" and not att.single
