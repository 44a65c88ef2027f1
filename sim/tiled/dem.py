"""The orbital terrain model of a tiled world, ``dem.tif``: what a stereo-photogrammetric DTM
(HiRISE-class, 1 m posts) of the route's coverage would give.

The true terrain (large-scale relief and the craters of at least two posts, as a 1 m DTM
resolves them) at the post centres, Gaussian-smoothed by ``dem_smoothing_posts`` (the DTM's
effective resolution), plus a vertical error that is smooth in space: independent values on a
lattice ``dem_correlation_m`` apart (seeded by the world's seed, from global lattice indices, so
continuous across tiles), bilinearly interpolated and scaled to an RMS of ``dem_sigma_m``.
Posts outside the covered tiles are NaN.

Format: one float32 band, tiled (256 px), zlib, with the orbital image's GeoTIFF tags
(ModelPixelScale, ModelTiepoint pixel-is-area at the north-west corner, GeoKeyDirectory) and
GDAL_NODATA "nan"; post (i, j)'s centre is (xmin + (j + 0.5) post, ymax - (i + 0.5) post).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from sim.craters.morphology import stamp_relief
from sim.tiled.noise import hash_uniform
from sim.tiled.world import TiledWorld

log = logging.getLogger(__name__)

DEM_ERROR_OCTAVE = 7001  # the error lattice's stream in hash_uniform (distinct from the terrain's octaves)
BILINEAR_RMS = 2.0 / (3.0 * math.sqrt(3.0))  # RMS of a bilinear interpolation of iid U(-1, 1) lattice values


def dem_error(seed: int, x: np.ndarray, y: np.ndarray, sigma_m: float, correlation_m: float) -> np.ndarray:
    """The DTM's vertical error (len(y), len(x)) on the grid of ``x`` (columns) and ``y`` (rows)."""
    u, v = np.asarray(x, float) / correlation_m, np.asarray(y, float) / correlation_m
    i0, j0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = (u - i0)[None, :], (v - j0)[:, None]
    I, J = i0[None, :], j0[:, None]
    h = lambda di, dj: hash_uniform(seed, DEM_ERROR_OCTAVE, I + di, J + dj)  # noqa: E731
    e = (1 - fv) * ((1 - fu) * h(0, 0) + fu * h(1, 0)) + fv * ((1 - fu) * h(0, 1) + fu * h(1, 1))
    return e * (sigma_m / BILINEAR_RMS)


def dem_block(world: TiledWorld, x: np.ndarray, y: np.ndarray, post_m: float) -> np.ndarray:
    """True terrain (len(y), len(x)) at the grid's posts (``x``, ``y`` ascending): the relief and the
    craters of at least two posts."""
    ext = (float(x[0]), float(x[-1]), float(y[0]), float(y[-1]))
    z = world.noise.grid(x, y)
    c = world.craters_near(ext, d_min_m=2.0 * post_m)
    return stamp_relief(z, ext, c.xy_m, c.diameter_m, c.degradation)


def write_dem(world: TiledWorld, tiles: list[tuple[int, int]], oc, seed: int, out: Path, progress=None) -> dict:
    """Write ``out / "dem.tif"`` over the covered ``tiles`` (``oc``: the orbital products config);
    returns its description for world.yaml."""
    import tifffile

    from sim.tiled.orbital import GEO_KEYS

    post, T = oc.dem_post_m, world.cfg.tile_size_m
    xmin = math.floor(min(ix for ix, _ in tiles) * T / post) * post
    xmax = math.ceil(max(ix + 1 for ix, _ in tiles) * T / post) * post
    ymin = math.floor(min(iy for _, iy in tiles) * T / post) * post
    ymax = math.ceil(max(iy + 1 for _, iy in tiles) * T / post) * post
    W, H = round((xmax - xmin) / post), round((ymax - ymin) / post)
    z = np.full((H, W), np.nan, np.float32)
    m = int(math.ceil(4 * oc.dem_smoothing_posts)) + 1  # margin for the smoothing
    for k, (ix, iy) in enumerate(tiles):
        j0, j1 = round((ix * T - xmin) / post), round(((ix + 1) * T - xmin) / post)
        r1, r0 = round((ymax - iy * T) / post), round((ymax - (iy + 1) * T) / post)  # rows, north first
        x = xmin + (np.arange(j0 - m, j1 + m) + 0.5) * post
        y = ymax - (np.arange(r1 + m - 1, r0 - m - 1, -1) + 0.5) * post  # ascending
        block = dem_block(world, x, y, post)
        if oc.dem_smoothing_posts > 0:
            block = gaussian_filter(block, oc.dem_smoothing_posts, mode="nearest")
        block = block + dem_error(seed, x, y, oc.dem_sigma_m, oc.dem_correlation_m)
        z[r0:r1, j0:j1] = block[::-1][m:-m, m:-m]
        if progress is not None:
            progress("dem", k + 1, len(tiles))
    geo = [(33550, "d", 3, (post, post, 0.0), False), (33922, "d", 6, (0.0, 0.0, 0.0, xmin, ymax, 0.0), False),
           (34735, "H", len(GEO_KEYS), GEO_KEYS, False), (42113, "s", 0, "nan", False)]
    desc = (f"fgslam sim {world.name} seed {seed}: terrain model, {post} m posts, vertical error {oc.dem_sigma_m} m RMS "
            f"correlated over {oc.dem_correlation_m} m, world frame (ENU m)")
    tifffile.imwrite(out / "dem.tif", z, tile=(256, 256), compression="zlib", photometric="minisblack",
                     extratags=geo, description=desc)
    log.info("wrote %s: %d x %d posts of %.2f m", out / "dem.tif", W, H, post)
    return {"file": "dem.tif", "post_m": post, "extent": [xmin, xmax, ymin, ymax], "sigma_m": oc.dem_sigma_m,
            "correlation_m": oc.dem_correlation_m, "smoothing_posts": oc.dem_smoothing_posts}
