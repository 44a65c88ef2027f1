"""Orbital products of a tiled world: the GeoTIFF's georeference (a crater at a known world
position appears at its pixel), independent readers agree, and the catalogs follow their
detection models."""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest
import tifffile
from PIL import Image

from sim.tiled.orbital import coverage_tiles, crater_detection_probability, write_orbital_products
from sim.tiled.presets import preset_config, resolve_tiled_config
from sim.tiled.world import TiledWorld


@cache
def _products(tmp):
    cfg = resolve_tiled_config(preset_config("cratered-3km", 6, {"tiled": {"size_m": 512.0, "orbital": {"corridor_m": 60.0}}}))
    world = TiledWorld(cfg.world, cfg.seed, cfg.tiled)
    c = world.craters_in((-100.0, 100.0, -100.0, 100.0))
    pick = c.subset((c.diameter_m > 14) & (c.diameter_m < 40) & (c.degradation < 0.15))
    assert len(pick), "the seeded world has a fresh crater near the origin"
    centre = pick.xy_m[np.argmax(pick.diameter_m)]
    path = centre + np.column_stack([np.linspace(-30, 30, 61), np.zeros(61)])
    res = write_orbital_products(world, path, cfg, tmp)
    assert res.coverage == coverage_tiles(world, path, cfg.tiled.orbital.corridor_m)
    return cfg, world, pick.subset([int(np.argmax(pick.diameter_m))]), res


@pytest.fixture(scope="module")
def products(tmp_path_factory):
    return _products(tmp_path_factory.mktemp("orbital"))


def test_crater_appears_at_its_pixel(products):
    cfg, _world, crater, res = products
    path = res.paths["orbital.tif"]
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        assert page.is_tiled and tif.is_geotiff
        geo = page.geotiff_tags
        img = page.asarray()
    gsd = cfg.sensors.orbital.gsd_m
    assert geo["ModelPixelScale"][:2] == [gsd, gsd]
    x0, y0 = geo["ModelTiepoint"][3], geo["ModelTiepoint"][4]
    assert (x0, y0) == (res.image_extent[0], res.image_extent[3])
    # the world file says the same (pixel centres)
    a, _, _, e, c, f = (float(v) for v in (path.with_suffix(".tfw")).read_text().split())
    assert (a, e, c - a / 2, f - e / 2) == pytest.approx((gsd, -gsd, x0, y0))
    # an independent reader decodes the same pixels
    assert np.array_equal(np.asarray(Image.open(path)), img)
    cx, cy = crater.xy_m[0]
    R = 0.5 * crater.diameter_m[0]
    col, row = (cx - x0) / gsd - 0.5, (y0 - cy) / gsd - 0.5
    ii, jj = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    # world offsets of every pixel from the crater centre
    dx, dy = (jj - col) * gsd, -(ii - row) * gsd
    r = np.hypot(dx, dy)
    dark = img < 0.6 * np.median(img)
    bowl, ring = r < 0.9 * R, (r > 1.6 * R) & (r < 2.5 * R)
    assert dark[bowl].mean() > 0.15  # the bowl holds a cast shadow ...
    assert dark[ring].mean() < 0.5 * dark[bowl].mean()  # ... its surroundings far less
    az = math.radians(cfg.tiled.orbital.sun_azimuth_deg)
    sun = np.array([math.cos(az), math.sin(az)])
    sel = bowl & dark
    centroid = np.array([dx[sel].mean(), dy[sel].mean()])
    assert centroid @ sun > 0.25 * R  # under the sunward rim, where a bowl's shadow falls
    assert np.linalg.norm(centroid - (centroid @ sun) * sun) < 0.35 * R


def test_crater_catalog_follows_its_detection_model(products):
    cfg, world, _, res = products
    oc, gsd = cfg.tiled.orbital, cfg.sensors.orbital.gsd_m
    cat = np.genfromtxt(res.paths["craters.csv"], delimiter=",", names=True)
    truth = np.genfromtxt(res.paths["craters_true.csv"], delimiter=",", names=True)
    assert res.counts["craters_true"] == len(truth)
    assert len(np.unique(truth["id"])) == len(truth)  # ids survive a float reader
    assert np.all(truth["depth"] <= 0.2 * truth["diameter"] + 1e-3)
    xmin, xmax, _ymin, _ymax = world.extent
    assert truth["x"].min() >= xmin and truth["x"].max() < xmax
    # big craters inside the coverage: found as often as the detection model says
    covered = set(res.coverage)
    T = world.cfg.tile_size_m
    inside = np.array([(math.floor(x / T), math.floor(y / T)) in covered for x, y in zip(truth["x"], truth["y"])])
    big = truth[inside & (truth["diameter"] / gsd >= 12)]
    assert len(big) >= 10
    from scipy.spatial import cKDTree

    tree = cKDTree(np.column_stack([cat["x"], cat["y"]]))
    d, k = tree.query(np.column_stack([big["x"], big["y"]]))
    found = (d < 0.25 * big["diameter"]) & (np.abs(cat["size"][k] / big["diameter"] - 1.0) < 0.3)
    p = crater_detection_probability(big["diameter"], big["degradation"], gsd, oc)
    assert abs(found.sum() - p.sum()) < 3.0 * np.sqrt(np.sum(p * (1 - p))) + 2
    assert found.mean() > 0.3  # degraded big craters are missed more often than fresh ones
    assert res.counts["craters"] == len(cat) and len(cat) > 0


def test_rock_catalog_sees_only_rocks_of_three_pixels(products):
    cfg, world, _, res = products
    det = cfg.sensors.orbital
    truth_ids = np.genfromtxt(res.paths["catalog_truth.csv"], delimiter=",", skip_header=1, dtype=np.int64)
    cat = np.genfromtxt(res.paths["catalog.csv"], delimiter=",", names=True)
    assert len(truth_ids) == len(cat) == res.counts["catalog"]
    true = truth_ids[truth_ids >= 0]
    assert len(true) > 10
    assert np.mean(truth_ids >= 0) == pytest.approx(det.precision, abs=0.1)
    rocks = world.rocks_in(res.image_extent)
    size = dict(zip(rocks.id.tolist(), rocks.diameter_m.tolist()))
    sizes = np.array([size[i] for i in true.tolist() if i in size])
    assert len(sizes) > 0.9 * len(true)
    assert sizes.min() >= det.min_size_px * det.gsd_m - 1e-9  # nothing under 3 px
