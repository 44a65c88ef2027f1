"""The out-of-catalog probe: a map matched where it is gives a fix; the same map moved over
another catalogued place of the path gives none, and the summary counts both."""

from __future__ import annotations

import numpy as np

from fgslam.bench.false_fixes import OutOfCatalogProbe, clopper_pearson_upper, summarize
from fgslam.relocalizer_config import RelocalizerConfig
from reloc.backend import LandmarkMap, PoseEstimate, Trajectory
from reloc.measurements import RockCatalog


def _world(seed=0):
    rng = np.random.default_rng(seed)
    xy = np.column_stack([rng.uniform(-20, 420, 9000), rng.uniform(-20, 20, 9000)])  # a 440 x 40 m strip
    size = np.exp(rng.normal(np.log(0.5), 0.4, len(xy)))
    cat = RockCatalog(xy + rng.normal(0, 0.03, xy.shape), size * np.exp(0.05 * rng.standard_normal(len(xy))),
                      np.ones(len(xy)))
    t = np.arange(0.0, 4001.0, 1.0)  # along x at 0.1 m/s
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, 0, 3] = 0.1 * t
    return xy, size, cat, Trajectory(t, T)


def _map_at(xy, size, x0):
    near = np.flatnonzero(np.hypot(xy[:, 0] - x0, xy[:, 1]) < 12.0)
    n = len(near)
    return LandmarkMap(near, np.column_stack([xy[near], np.zeros(n)]), np.tile(np.eye(3) * 1e-4, (n, 1, 1)),
                       size[near], np.full(n, 3), "rocks")


def test_a_map_moved_over_another_catalogued_place_gives_no_fix():
    xy, size, cat, truth = _world()
    cfg = RelocalizerConfig(window_path_m=0.0, min_new_observations=0)
    probe = OutOfCatalogProbe("rocks", cat, cfg, truth)
    for t in (100.0, 2000.0, 3500.0):
        x0 = 0.1 * t
        T = np.eye(4)
        T[0, 3] = x0
        probe.attempt({"rocks": _map_at(xy, size, x0)}, PoseEstimate(t, T, np.diag([0.04, 0.04, 1e-4, 1e-5, 1e-5, 1e-4])))
    first, *later = probe.records
    assert first["skipped"] == "no place far enough yet"  # 10 m into the strip: nowhere far enough
    for rec in later:
        assert rec["home"] == "fix" and rec["home_error_m"] < 0.1
        assert rec["away"] != "fix" and rec["away_shift_m"] >= 24.0
    s = summarize(probe.records, {"rocks": 1e-3})["rocks"]
    assert s["attempts"] == 3 and s["fixes"] == 3 and s["out_of_catalog_attempts"] == 2 and s["false_fixes"] == 0
    assert s["false_fix_rate_upper95"] == clopper_pearson_upper(0, 2)


def test_clopper_pearson_upper_bound_matches_its_closed_form():
    # with no event in n, the one-sided upper bound is 1 - 0.05 ** (1 / n)
    for n in (1, 10, 3000):
        assert abs(clopper_pearson_upper(0, n) - (1 - 0.05 ** (1 / n))) < 1e-12
    assert clopper_pearson_upper(5, 5) == 1.0 and np.isnan(clopper_pearson_upper(0, 0))


def test_a_lost_estimate_is_not_probed_away():
    """Lost (sigma above lost_sigma_m), the relocalizer searches the whole catalog, which holds
    the map's own place wherever the map is moved: the probe skips the away attempt, and the
    home attempt still finds the map where it is."""
    xy, size, cat, truth = _world()
    cfg = RelocalizerConfig(window_path_m=0.0, min_new_observations=0)
    probe = OutOfCatalogProbe("rocks", cat, cfg, truth)
    t, x0 = 3500.0, 350.0
    T = np.eye(4)
    T[0, 3] = x0
    lost = np.diag([cfg.lost_sigma_m**2 * 4, cfg.lost_sigma_m**2 * 4, 1e-4, 1e-5, 1e-5, 1e-4])
    probe.attempt({"rocks": _map_at(xy, size, x0)}, PoseEstimate(t, T, lost))
    (rec,) = probe.records
    assert rec["skipped"] == "whole-catalog search (lost or no prior)" and "away" not in rec
    assert rec["sigma_m"] > cfg.lost_sigma_m
    assert rec["home"] == "fix" and rec["home_error_m"] < 0.1
    s = summarize(probe.records, {"rocks": 1e-3})["rocks"]
    assert s["out_of_catalog_attempts"] == 0 and s["skipped"] == {"whole-catalog search (lost or no prior)": 1}
