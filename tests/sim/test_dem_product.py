"""The tiled worlds' terrain model (dem.tif): read back by fgslam's reader and by tifffile with its
georeference, close to the true terrain by its stated error, that error smooth, seeded and of
the stated RMS, no data outside the coverage, and its settings checked."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import tifffile
import yaml
from scipy.ndimage import gaussian_filter

from fgslam.io.dem_tif import read_dem
from reloc.errors import ConfigError
from sim.tiled.config import TiledConfigError
from sim.tiled.dem import dem_block, dem_error, write_dem
from sim.tiled.orbital import GEO_KEYS, coverage_tiles, write_orbital_products
from sim.tiled.outputs import simulate_to_bag
from sim.tiled.presets import preset_config, resolve_tiled_config
from sim.tiled.world import TiledWorld


def _world(seed=6):
    cfg = resolve_tiled_config(preset_config("cratered-3km", seed, {"tiled": {"size_m": 512.0, "orbital": {"corridor_m": 40.0}}}))
    return cfg, TiledWorld(cfg.world, cfg.seed, cfg.tiled)


# an L: the corner of its bounding box away from it (north-west) is not covered
PATH = np.vstack([np.column_stack([np.linspace(-150, 150, 301), np.zeros(301)]),
                  np.column_stack([np.full(250, 150.0), np.linspace(1, 250, 250)])])


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    cfg, world = _world()
    out = tmp_path_factory.mktemp("dem")
    tiles = coverage_tiles(world, PATH, cfg.tiled.orbital.corridor_m)
    desc = write_dem(world, tiles, cfg.tiled.orbital, cfg.seed, out)
    return cfg, world, tiles, desc, out


def test_the_dem_reads_back_georeferenced_and_near_the_true_terrain(written):
    cfg, world, _tiles, desc, out = written
    with tifffile.TiffFile(out / "dem.tif") as tif:
        page = tif.pages[0]
        assert page.dtype == np.float32 and page.is_tiled
        tags = {t.code: t.value for t in page.tags.values()}
    assert tags[33550][:2] == (1.0, 1.0) and tags[33922][3:5] == (desc["extent"][0], desc["extent"][3])
    dem = read_dem(out / "dem.tif")
    assert dem.extent == tuple(desc["extent"])
    rng = np.random.default_rng(0)
    xy = PATH[rng.integers(0, len(PATH), 400)] + rng.uniform(-15, 15, (400, 2))
    z = np.array([dem.sample(x, y).z_m for x, y in xy])
    err = z - world.height_at(xy)
    sigma = cfg.tiled.orbital.dem_sigma_m
    # the stated error (a few independent 25 m cells here, so loosely) plus the smoothing's
    assert 0.3 * sigma < np.sqrt(np.mean(err**2)) < 2.0 * sigma


def test_the_error_is_smooth_seeded_and_of_the_stated_rms():
    x = np.arange(-2000.0, 2000.0, 5.0)
    e = dem_error(3, x, x, 0.15, 25.0)
    assert np.sqrt(np.mean(e**2)) == pytest.approx(0.15, rel=0.1)
    assert abs(np.mean(e)) < 0.02
    assert np.max(np.abs(np.diff(e, axis=1))) < 0.15 * 5.0 / 25.0 * 6  # no jumps: bounded slope
    assert np.array_equal(e, dem_error(3, x, x, 0.15, 25.0))
    assert not np.allclose(e, dem_error(4, x, x, 0.15, 25.0))
    # tile borders: the same posts computed in two blocks agree
    assert np.array_equal(dem_error(3, x[:400], x[:10], 0.15, 25.0), e[:10, :400])


def test_outside_the_coverage_is_nan(written):
    _cfg, world, tiles, desc, out = written
    dem = read_dem(out / "dem.tif")
    T = world.cfg.tile_size_m
    xmin, xmax, ymin, ymax = desc["extent"]
    for ix in range(round(xmin / T), round(xmax / T)):
        for iy in range(round(ymin / T), round(ymax / T)):
            s = dem.sample((ix + 0.5) * T, (iy + 0.5) * T)
            assert (s is not None) == ((ix, iy) in tiles), (ix, iy)
    assert np.isnan(dem.z_m).any()


@pytest.mark.parametrize("key, value", [("dem_post_m", 0.0), ("dem_correlation_m", -1.0), ("dem_sigma_m", float("nan")),
                                        ("dem_smoothing_posts", -0.5)])
def test_bad_dem_settings_name_the_key(key, value):
    cfg, _ = _world()
    with pytest.raises(TiledConfigError, match=key):
        dataclasses.replace(cfg.tiled.orbital, **{key: value})


# -- the product as written: tags, exact values, streaming, the route's error ---------------------

def _write(world, tiles, out, seed=6, route_xyz=None, **settings):
    """The model of ``tiles`` with the orbital settings ``settings`` written into ``out``."""
    cfg, _ = _world()
    oc = dataclasses.replace(cfg.tiled.orbital, **settings)
    out.mkdir(parents=True, exist_ok=True)
    info = write_dem(world, tiles, oc, seed, out, route_xyz=route_xyz, base_height_m=cfg.rover.base_height_m)
    return oc, info, tifffile.imread(out / "dem.tif")


def _posts(info):
    """The post centres (x ascending, y north first) of a written model."""
    xmin, _, _, ymax = info["extent"]
    p = info["post_m"]
    return xmin + (np.arange(info["width_posts"]) + 0.5) * p, ymax - (np.arange(info["height_posts"]) + 0.5) * p


def _reference(world, oc, seed, x, y, pad=12):
    """The model recomputed in one piece (no blocks) at the posts ``x`` (ascending), ``y`` (north first),
    NaN nowhere: what the block-wise writer must reproduce inside the coverage."""
    p = oc.dem_post_m
    xs = np.concatenate([x[0] - p * np.arange(pad, 0, -1), x, x[-1] + p * np.arange(1, pad + 1)])
    ys = np.concatenate([y[-1] - p * np.arange(pad, 0, -1), y[::-1], y[0] + p * np.arange(1, pad + 1)])
    z = dem_block(world, xs, ys, d_min_m=2.0 * p)
    if oc.dem_smoothing_posts > 0:
        z = gaussian_filter(z, oc.dem_smoothing_posts, mode="nearest")
    z = z + dem_error(seed, xs, ys, oc.dem_sigma_m, oc.dem_correlation_m)
    return z[pad:-pad, pad:-pad][::-1]


def test_the_file_carries_the_geotiff_tags_and_a_description(written):
    _cfg, world, tiles, desc, out = written
    with tifffile.TiffFile(out / "dem.tif") as tif:
        page = tif.pages[0]
        tags = {t.code: t.value for t in page.tags.values()}
        assert page.dtype == np.float32 and page.samplesperpixel == 1 and page.shape == (desc["height_posts"], desc["width_posts"])
        assert (page.tilelength, page.tilewidth) == (256, 256)
        assert page.compression == tifffile.COMPRESSION.ADOBE_DEFLATE  # zlib
        text = page.description
    xmin, xmax, ymin, ymax = desc["extent"]
    assert tags[33550] == (1.0, 1.0, 0.0)
    assert tags[33922] == (0.0, 0.0, 0.0, xmin, ymax, 0.0)
    assert tags[34735] == GEO_KEYS
    assert tags[42113] == "nan"
    # the covered tiles' bounding box, in whole posts
    T = world.cfg.tile_size_m
    assert (xmin, xmax) == (min(t[0] for t in tiles) * T, (max(t[0] for t in tiles) + 1) * T)
    assert (ymin, ymax) == (min(t[1] for t in tiles) * T, (max(t[1] for t in tiles) + 1) * T)
    assert desc["valid_posts"] == len(tiles) * round(T) ** 2
    for part in ("cratered-3km", "seed 6", "1.0 m posts", "0.15 m RMS", "25.0 m"):
        assert part in text


def test_the_fast_terrain_path_is_the_true_terrain():
    _, world = _world()
    x = np.arange(-70.0, 70.0) + 0.5  # across tile borders (64 m) on both axes
    y = np.arange(-20.0, 90.0) + 0.5
    z = dem_block(world, x, y)
    X, Y = np.meshgrid(x, y)
    truth = world.height_at(np.column_stack([X.ravel(), Y.ravel()])).reshape(X.shape)
    assert np.max(np.abs(z - truth)) < 1e-3


def test_blocks_join_without_seams_and_the_same_seed_gives_the_same_bytes(written, tmp_path):
    """A model over two 256-post blocks (and many tiles) equals the same model computed in one
    piece; writing it again gives the same values, another seed another error on the same terrain."""
    cfg, world, tiles, desc, out = written
    oc = cfg.tiled.orbital
    z = tifffile.imread(out / "dem.tif")
    assert z.shape[0] > 256 and z.shape[1] > 256  # block borders at row and column 256
    x, y = _posts(desc)
    ref = _reference(world, oc, cfg.seed, x, y)
    have = np.isfinite(z)
    assert np.max(np.abs(z[have] - ref[have])) < 1e-4  # float32 rounding
    # no jump at the block borders beyond the terrain's own post-to-post variation
    for d, border in ((np.abs(np.diff(z, axis=1)), np.s_[:, 255]), (np.abs(np.diff(z, axis=0)), np.s_[255, :])):
        assert np.nanpercentile(d[border], 90) < 2 * np.nanpercentile(d, 90)
    _, _, again = _write(world, tiles, tmp_path / "again", seed=cfg.seed)
    assert again.tobytes() == z.tobytes()
    _, _, other = _write(world, tiles, tmp_path / "other", seed=cfg.seed + 1)
    d = (other - z)[have]
    # the terrain is the same, the errors independent: their difference has sqrt(2) sigma RMS
    assert 0.7 * np.sqrt(2) * oc.dem_sigma_m < np.sqrt(np.mean(d**2)) < 1.3 * np.sqrt(2) * oc.dem_sigma_m
    assert np.array_equal(np.isnan(other), ~have)


def test_the_error_has_the_stated_rms_over_the_coverage(written, tmp_path):
    cfg, world, tiles, _, _ = written
    oc, info, z = _write(world, tiles, tmp_path, seed=cfg.seed, dem_smoothing_posts=0.0, dem_correlation_m=10.0)
    x, y = _posts(info)
    truth = dem_block(world, x, y[::-1], d_min_m=2.0 * oc.dem_post_m)[::-1]
    err = (z - truth)[np.isfinite(z)]
    assert len(err) == info["valid_posts"]
    assert np.sqrt(np.mean(err**2)) == pytest.approx(oc.dem_sigma_m, rel=0.25)
    assert abs(np.mean(err)) < 0.25 * oc.dem_sigma_m
    # smoothed, against the true terrain itself: the stated error and the smoothing's share
    _, info, z = _write(world, tiles, tmp_path / "smoothed", seed=cfg.seed)
    truth = dem_block(world, x, y[::-1])[::-1]
    rms = np.sqrt(np.nanmean((z - truth) ** 2))
    assert 0.5 * oc.dem_sigma_m < rms < 2.0 * oc.dem_sigma_m


def test_the_route_height_error_is_the_model_read_at_the_true_positions(written, tmp_path):
    """The writer's route figure is what a reader of the file gets: the model bilinearly at the
    true (x, y) plus the base height, against the true z (points in several blocks and tiles,
    some on post centres and on block borders)."""
    cfg, world, tiles, _, _ = written
    rng = np.random.default_rng(1)
    xy = np.vstack([PATH[rng.integers(0, len(PATH), 300)] + rng.uniform(-20, 20, (300, 2)),
                    [[-63.5, 0.5], [0.5, 64.5], [63.5, 63.5]],  # post centres: first row / column of a block
                    [[64.0, 0.25], [150.2, 63.99]]])
    z_true = world.height_at(xy) + cfg.rover.base_height_m + rng.normal(0.0, 0.05, len(xy))
    _, info, _ = _write(world, tiles, tmp_path, seed=cfg.seed, route_xyz=np.column_stack([xy, z_true]))
    dem = read_dem(tmp_path / "dem.tif")
    s = [dem.sample(x, y) for x, y in xy]
    ok = np.array([v is not None for v in s])
    assert ok.sum() > 290
    err = np.array([v.z_m for v in np.array(s, dtype=object)[ok]]) + cfg.rover.base_height_m - z_true[ok]
    assert info["route_height_samples"] == ok.sum()
    assert info["route_height_rmse_m"] == pytest.approx(np.sqrt(np.mean(err**2)), abs=1e-4)
    assert info["route_height_mean_m"] == pytest.approx(np.mean(err), abs=1e-4)


def test_write_dem_false_writes_no_model_and_true_describes_it(tmp_path):
    cfg, world = _world()
    path = np.column_stack([np.linspace(-20, 20, 41), np.zeros(41)])
    cfg = dataclasses.replace(cfg, tiled=dataclasses.replace(cfg.tiled, orbital=dataclasses.replace(
        cfg.tiled.orbital, write_image=False, corridor_m=10.0)))
    res = write_orbital_products(world, path, cfg, tmp_path)
    assert res.paths["dem.tif"] == tmp_path / "dem.tif" and (tmp_path / "dem.tif").is_file()
    assert res.dem["file"] == "dem.tif" and res.counts["dem_posts"] == res.dem["valid_posts"] > 0
    assert "route_height_rmse_m" not in res.dem  # no ground truth given
    off = dataclasses.replace(cfg, tiled=dataclasses.replace(cfg.tiled, orbital=dataclasses.replace(
        cfg.tiled.orbital, write_dem=False)))
    (tmp_path / "off").mkdir()
    res = write_orbital_products(world, path, off, tmp_path / "off")
    assert not (tmp_path / "off" / "dem.tif").exists() and "dem.tif" not in res.paths and res.dem is None


def test_a_bad_dem_setting_in_a_config_file_names_the_key():
    with pytest.raises(ConfigError, match=r"tiled\.orbital\.dem_post_m"):
        preset_config("cratered-3km", 0, {"tiled": {"orbital": {"dem_post_m": -1.0}}})


def test_a_kilometre_run_records_the_model_and_its_error_on_the_route(tmp_path):
    """world.yaml's dem block: the file, its settings and the height error measured on the
    driven route against the ground truth."""
    cfg = preset_config("rocky-1km", 3, {"traverse": {"distance_m": 5.0}, "tiled": {
        "size_m": 512.0, "orbital": {"write_image": False, "corridor_m": 20.0}}})
    run = simulate_to_bag(cfg, tmp_path)
    doc = yaml.safe_load((tmp_path / "world.yaml").read_text())["dem"]
    assert doc["file"] == "dem.tif" and (tmp_path / "dem.tif").is_file()
    assert (doc["post_m"], doc["sigma_m"], doc["correlation_m"], doc["smoothing_posts"]) == (1.0, 0.15, 25.0, 1.0)
    assert doc["route_height_samples"] == pytest.approx(run.stats["distance_m"] / 0.1, rel=0.2)
    assert 0.02 < doc["route_height_rmse_m"] < 0.5
