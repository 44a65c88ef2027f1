"""The tiled worlds' terrain model (dem.tif): read back by fgslam's reader and by tifffile with its
georeference, close to the true terrain by its stated error, that error smooth, seeded and of
the stated RMS, no data outside the coverage, and its settings checked."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import tifffile

from fgslam.io.dem_tif import read_dem
from sim.tiled.config import TiledConfigError
from sim.tiled.dem import dem_error, write_dem
from sim.tiled.orbital import coverage_tiles
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
    cfg, world, tiles, desc, out = written
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
