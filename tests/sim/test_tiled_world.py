"""Tiled worlds: tiles from any generation order are bit-identical, seams match, the rock and
crater populations follow their models, region queries agree with the tiles, caches stay bounded."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim.config import SimConfigError
from sim.craters import CraterSFD
from sim.errors import SimError
from sim.rock_sfd import GolombekRapp
from sim.tiled.presets import TILED_PRESETS, preset_config, resolve_tiled_config
from sim.tiled.world import TiledWorld


def _world(name="rocky-1km", seed=3, **tiled):
    cfg = resolve_tiled_config(preset_config(name, seed))
    return TiledWorld(name, seed, dataclasses.replace(cfg.tiled, **tiled))


def test_a_tile_is_the_same_whatever_was_generated_before():
    a = _world()
    first = a.tile(2, -1)
    b = _world()
    for key in ((3, -1), (2, 0), (1, -1), (2, -2), (5, 5)):
        b.tile(*key)
    again = b.tile(2, -1)
    assert np.array_equal(first.terrain.z_m, again.terrain.z_m)
    for f in ("xy_m", "diameter_m", "id", "xyz_m", "semi_m", "yaw_rad", "shape_error", "ejecta"):
        assert np.array_equal(getattr(first.rocks, f), getattr(again.rocks, f)), f
    assert np.array_equal(first.craters.id, again.craters.id)
    assert np.array_equal(a._make_meshes((2, -1))[0], b._make_meshes((2, -1))[0])
    other = _world(seed=4).tile(2, -1)
    assert not np.array_equal(first.terrain.z_m, other.terrain.z_m)


def test_neighbouring_tiles_meet_without_seams_and_queries_agree():
    w = _world()
    left, right = w.tile(0, 0), w.tile(1, 0)
    res, m = w.cfg.resolution_m, w.cfg.tile_margin_m
    k = round(m / res)
    n = round(w.cfg.tile_size_m / res)
    # the column at x = 64 m: last core column of the left tile, first of the right one
    assert np.allclose(left.terrain.z_m[:, k + n], right.terrain.z_m[:, k], atol=1e-9)
    hm = w.heightmap((50.0, 80.0, 10.0, 30.0))
    pts = np.column_stack([np.linspace(51, 79, 50), np.linspace(11, 29, 50)])
    assert np.allclose(hm.height_at(pts), w.height_at(pts), atol=0.05)
    rocks = w.rocks_in((0.0, 128.0, 0.0, 64.0))
    assert len(rocks) == len(left.rocks) + len(right.rocks)
    assert len(np.unique(rocks.id)) == len(rocks)


def test_background_rocks_follow_golombek_rapp():
    w = _world(seed=5)
    gr = GolombekRapp(0.15)
    rocks = [w.tile(i, j).rocks for i in range(2) for j in range(2)]
    d = np.concatenate([r.diameter_m[~r.ejecta] for r in rocks])
    area = 4 * 64.0**2
    for lo, hi in ((0.1, 0.2), (0.2, 0.5), (0.5, 1.0), (1.0, 3.0)):
        lam = area * (gr.cumulative_number(lo) - gr.cumulative_number(hi))
        n = np.sum((d >= lo) & (d < hi))
        assert abs(n - lam) < 4 * np.sqrt(lam) + 2, (lo, hi, n, lam)
    # fractional area of rocks >= 0.5 m against F_k(0.5) - F_k(3) (discs of the diameter)
    frac = np.sum(np.pi / 4 * d[d >= 0.5] ** 2) / area
    assert frac == pytest.approx(gr.cumulative_area(0.5) - gr.cumulative_area(3.0), rel=0.25)


def test_world_craters_follow_the_model_in_every_size_class():
    w = _world("cratered-3km", seed=2)
    sfd = w.sfd
    ext = (-500.0, 500.0, -500.0, 500.0)
    c = w.craters_in(ext)
    for lo, hi in ((1.0, 2.0), (2.0, 8.0), (8.0, 40.0), (40.0, 200.0)):  # across the cell classes
        lam = sfd.expected_count(1e6, lo, hi)
        n = np.sum((c.diameter_m >= lo) & (c.diameter_m < hi))
        assert abs(n - lam) < 4 * np.sqrt(lam) + 2, (lo, hi, n, lam)
    inside = (c.xy_m[:, 0] >= -500) & (c.xy_m[:, 0] < 500) & (c.xy_m[:, 1] >= -500) & (c.xy_m[:, 1] < 500)
    assert inside.all() and len(np.unique(c.id)) == len(c)
    assert isinstance(sfd, CraterSFD) and sfd.saturation_ratio(np.array([5.0]))[0] > 1  # 3 Gyr: saturated


def test_fresh_craters_throw_blocks_and_the_caches_stay_bounded():
    w = _world("rocky-1km", seed=1, cache_tiles=4)
    for i in range(10):
        w.tile(i, 0)
    assert len(w._tiles) == 4 and w.tiles_made == 10
    w.tile(0, 0)  # evicted: made again, identical
    assert w.tiles_made == 11
    big = w.craters_in((-700.0, 700.0, -700.0, 700.0))
    fresh = big.subset((big.diameter_m > 30) & (big.degradation < 0.1))
    assert len(fresh)
    c = fresh.xy_m[np.argmax(fresh.diameter_m)]
    r = 0.5 * fresh.diameter_m.max()
    near = w.rocks_in((c[0] - 2 * r, c[0] + 2 * r, c[1] - 2 * r, c[1] + 2 * r))
    dist = np.linalg.norm(near.xy_m - c, axis=1)
    ring = near.ejecta & (dist > r) & (dist < 2 * r)
    assert ring.sum() > 20  # blocks concentrated round the rim


def test_tiled_configs_reject_what_streaming_cannot_honour():
    with pytest.raises(SimConfigError, match="target_drift_pct"):
        resolve_tiled_config(preset_config("plains-2km", 0, {"sensors": {"cmd": {"target_drift_pct": 2.0}}}))
    with pytest.raises(SimConfigError, match="duration_s"):
        resolve_tiled_config(preset_config("plains-2km", 0, {"traverse": {"duration_s": 100.0}}))
    with pytest.raises(SimConfigError, match="unknown kilometre preset"):
        preset_config("plains-9km")
    cfg = resolve_tiled_config(preset_config("sparse-5km", 0, {"traverse": {"distance_m": 20000.0}}))
    assert cfg.tiled.size_m == pytest.approx(2 * TILED_PRESETS["sparse-5km"].size_m)  # grown for the length
    with pytest.raises(SimError, match="tiled.rocks.k is not set"):
        TiledWorld("x", 0, dataclasses.replace(cfg.tiled, rocks=dataclasses.replace(cfg.tiled.rocks, k=None)))


def test_sparse_ground_presets_give_the_smoother_its_sparse_model_from_the_gyro_datasheet():
    from fgslam.smoother.config import SmootherConfig
    from reloc.config import config_from_dict
    from sim.tiled.presets import backend_calibration

    for name, preset in TILED_PRESETS.items():
        cfg = preset_config(name, 0)
        isam2 = backend_calibration(cfg)["isam2"]
        config_from_dict(SmootherConfig, isam2)  # the smoother accepts what `fgslam sim` writes
        odo, imu = isam2["odometry"], cfg.sensors.imu
        if preset.sparse_ground:
            assert odo["sigma_rot_radpsqrts"] == imu.gyro_noise_radps_rsqrt_hz  # the bias is a variable now
            assert odo["yaw_rate_bias_sigma_radps"] == imu.gyro_bias_sigma_radps > 0
            assert odo["yaw_rate_bias_walk_radps_rsqrt_s"] == imu.gyro_bias_walk_radps_rsqrt_s
            assert odo["slip_sigma"] > 0 and isam2["calibration"]["roll_sigma_deg"] == 0.0
        else:  # the bias folded into the rotation noise, no slip variable, the roll estimated
            assert odo["sigma_rot_radpsqrts"] > imu.gyro_noise_radps_rsqrt_hz
            assert not {"yaw_rate_bias_sigma_radps", "slip_sigma"} & set(odo)
            assert "roll_sigma_deg" not in isam2["calibration"]
    assert [n for n, p in TILED_PRESETS.items() if p.sparse_ground] == ["sparse-5km"]
