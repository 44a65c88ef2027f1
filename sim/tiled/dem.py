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

The model is computed and written one 256-post block at a time (each block with a margin that
the smoothing needs, so blocks join without seams), so memory does not grow with the coverage.
Given the true base_link positions of the drive, the writer also measures the height error a
user of the model sees on the route: the model bilinearly at the true (x, y), plus the base
height, minus the true z (a figure for the documentation; nothing downstream uses it).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from sim.craters.morphology import stamp_relief
from sim.tiled.noise import hash_uniform
from sim.tiled.world import TiledWorld

log = logging.getLogger(__name__)

DEM_ERROR_OCTAVE = 7001  # the error lattice's stream in hash_uniform (distinct from the terrain's octaves)
BILINEAR_RMS = 2.0 / (3.0 * math.sqrt(3.0))  # RMS of a bilinear interpolation of iid U(-1, 1) lattice values
DEM_TILE_POSTS = 256  # the GeoTIFF's tiles, and the blocks it is computed in
SMOOTHING_TRUNCATE = 4.0  # the Gaussian kernel reaches this many sigmas (scipy's default)
GEOREFERENCE = ("GeoTIFF ModelPixelScale + ModelTiepoint, pixel-is-area: post (row, col) covers x in xmin + post "
                "[col, col + 1], y in ymax - post [row + 1, row], its height at the centre; user-defined metric "
                "CRS = the simulator's world frame (x east, y north, z up, metres); GDAL_NODATA nan outside the coverage")


def dem_error(seed: int, x: np.ndarray, y: np.ndarray, sigma_m: float, correlation_m: float) -> np.ndarray:
    """The DTM's vertical error (len(y), len(x)) on the grid of ``x`` (columns) and ``y`` (rows)."""
    u, v = np.asarray(x, float) / correlation_m, np.asarray(y, float) / correlation_m
    i0, j0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = (u - i0)[None, :], (v - j0)[:, None]
    I, J = i0[None, :], j0[:, None]
    h = lambda di, dj: hash_uniform(seed, DEM_ERROR_OCTAVE, I + di, J + dj)
    e = (1 - fv) * ((1 - fu) * h(0, 0) + fu * h(1, 0)) + fv * ((1 - fu) * h(0, 1) + fu * h(1, 1))
    return e * (sigma_m / BILINEAR_RMS)


def dem_block(world: TiledWorld, x: np.ndarray, y: np.ndarray, d_min_m: float = 0.0) -> np.ndarray:
    """True terrain (len(y), len(x)) on the grid of ``x`` (columns) and ``y`` (rows), both ascending
    and evenly spaced, at least 2 each: the relief and the craters of diameter >= ``d_min_m``. With
    ``d_min_m`` 0 it is :meth:`TiledWorld.height_at` at the grid's points (to rounding), ~20x faster."""
    ext = (float(x[0]), float(x[-1]), float(y[0]), float(y[-1]))
    z = world.noise.grid(x, y)
    c = world.craters_near(ext, d_min_m=d_min_m)
    return stamp_relief(z, ext, c.xy_m, c.diameter_m, c.degradation)


def dem_grid(tiles: list[tuple[int, int]], tile_size_m: float, post_m: float) -> tuple[tuple[float, float, float, float], int, int]:
    """The model's extent (xmin, xmax, ymin, ymax), the covered tiles' bounding box snapped
    outwards to whole posts, and its width and height in posts."""
    T = tile_size_m
    xmin = math.floor(min(ix for ix, _ in tiles) * T / post_m) * post_m
    xmax = math.ceil(max(ix + 1 for ix, _ in tiles) * T / post_m) * post_m
    ymin = math.floor(min(iy for _, iy in tiles) * T / post_m) * post_m
    ymax = math.ceil(max(iy + 1 for _, iy in tiles) * T / post_m) * post_m
    return (xmin, xmax, ymin, ymax), round((xmax - xmin) / post_m), round((ymax - ymin) / post_m)


def coverage_mask(covered: set[tuple[int, int]], tile_size_m: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(len(y), len(x)) True where the point (x[j], y[i]) lies in a covered tile."""
    tx = np.floor(np.asarray(x, float) / tile_size_m).astype(np.int64)
    ty = np.floor(np.asarray(y, float) / tile_size_m).astype(np.int64)
    ux, jx = np.unique(tx, return_inverse=True)
    uy, jy = np.unique(ty, return_inverse=True)
    cov = np.array([[(a, b) in covered for a in ux.tolist()] for b in uy.tolist()], dtype=bool).reshape(len(uy), len(ux))
    return cov[np.ix_(jy, jx)]


def write_dem(world: TiledWorld, tiles: list[tuple[int, int]], oc, seed: int, out: Path, progress=None, *,
              route_xyz: np.ndarray | None = None, base_height_m: float = 0.0) -> dict:
    """Write ``out / "dem.tif"`` over the covered ``tiles`` (``oc``: the orbital products config),
    block by block; returns its description for world.yaml. With ``route_xyz`` (N, 3), true
    base_link positions, the description holds ``route_height_rmse_m`` (and the mean and count):
    the model at their (x, y) plus ``base_height_m`` against their z."""
    import tifffile

    from sim.tiled.orbital import GEO_KEYS

    t0 = time.perf_counter()
    post, T, n = oc.dem_post_m, world.cfg.tile_size_m, DEM_TILE_POSTS
    (xmin, xmax, ymin, ymax), W, H = dem_grid(tiles, T, post)
    covered = set(tiles)
    radius = int(SMOOTHING_TRUNCATE * oc.dem_smoothing_posts + 0.5) if oc.dem_smoothing_posts > 0 else 0
    m = radius + 1  # exact smoothed values one post beyond the block (for the route's bilinear cells)
    blocks = [(r0, c0) for r0 in range(0, H, n) for c0 in range(0, W, n)]  # row-major from the north
    route = _route_cells(route_xyz, xmin, ymax, post, W, H, n)
    acc = {"n": 0, "sum": 0.0, "sum2": 0.0, "valid": 0}

    def blocks_iter():
        for k, (r0, c0) in enumerate(blocks):
            rows, cols = np.arange(r0 - m, r0 + n + m), np.arange(c0 - m, c0 + n + m)
            x, y = xmin + (cols + 0.5) * post, ymax - (rows + 0.5) * post  # y: north first
            inside = coverage_mask(covered, T, x, y)
            inside &= ((rows >= 0) & (rows < H))[:, None] & ((cols >= 0) & (cols < W))[None, :]
            if not inside[m:m + n, m:m + n].any():
                block = np.full((n, n), np.nan, np.float32)
            else:
                z = dem_block(world, x, y[::-1], d_min_m=2.0 * post)
                if oc.dem_smoothing_posts > 0:
                    z = gaussian_filter(z, oc.dem_smoothing_posts, mode="nearest", truncate=SMOOTHING_TRUNCATE)
                z = z + dem_error(seed, x, y[::-1], oc.dem_sigma_m, oc.dem_correlation_m)
                z = np.where(inside, z[::-1], np.nan).astype(np.float32)  # north first, as written
                if (r0, c0) in route:
                    _measure(z, route[(r0, c0)], r0 - m, c0 - m, base_height_m, acc)
                block = z[m:m + n, m:m + n]
                acc["valid"] += int(np.isfinite(block).sum())
            if progress is not None:
                progress("dem", k + 1, len(blocks))
            yield np.ascontiguousarray(block)

    geo = [(33550, "d", 3, (post, post, 0.0), False), (33922, "d", 6, (0.0, 0.0, 0.0, xmin, ymax, 0.0), False),
           (34735, "H", len(GEO_KEYS), GEO_KEYS, False), (42113, "s", 0, "nan", False)]
    desc = (f"fgslam sim {world.name} seed {seed}: terrain model (stereo DTM) of the route's coverage, heights in "
            f"metres in the world frame (ENU m), {post} m posts, effective resolution Gaussian sigma "
            f"{oc.dem_smoothing_posts} posts, vertical error {oc.dem_sigma_m} m RMS correlated over "
            f"{oc.dem_correlation_m} m, NaN outside the coverage")
    tifffile.imwrite(out / "dem.tif", blocks_iter(), shape=(H, W), dtype=np.float32, tile=(n, n), compression="zlib",
                     photometric="minisblack", extratags=geo, bigtiff=H * W * 4 > 2**31, description=desc)
    info = {"file": "dem.tif", "post_m": post, "extent": [xmin, xmax, ymin, ymax], "width_posts": W, "height_posts": H,
            "tile_posts": n, "valid_posts": acc["valid"], "sigma_m": oc.dem_sigma_m,
            "correlation_m": oc.dem_correlation_m, "smoothing_posts": oc.dem_smoothing_posts,
            "crater_min_diameter_m": 2.0 * post, "nodata": "nan", "georeference": GEOREFERENCE}
    wall = time.perf_counter() - t0
    if acc["n"]:
        rmse, mean = math.sqrt(acc["sum2"] / acc["n"]), acc["sum"] / acc["n"]
        info.update(route_height_rmse_m=round(rmse, 4), route_height_mean_m=round(mean, 4), route_height_samples=acc["n"])
        log.info("wrote %s: %d x %d posts of %.2f m (%d with data), %.1f MB in %.1f s; on the route (%d points) the "
                 "model + base height - true z: RMSE %.3f m, mean %+.3f m", out / "dem.tif", W, H, post, acc["valid"],
                 (out / "dem.tif").stat().st_size / 1e6, wall, acc["n"], rmse, mean)
    else:
        log.info("wrote %s: %d x %d posts of %.2f m (%d with data), %.1f MB in %.1f s", out / "dem.tif", W, H, post,
                 acc["valid"], (out / "dem.tif").stat().st_size / 1e6, wall)
    return info


def _route_cells(route_xyz, xmin: float, ymax: float, post: float, W: int, H: int, n: int) -> dict:
    """The route's points by the block of their bilinear cell's north-west post:
    {(r0, c0): (i, j, fu, fv, z)}, the cell's row and column, the point's fractions in it and its
    true z (points outside the posts' centres left out)."""
    if route_xyz is None or len(route_xyz) == 0:
        return {}
    p = np.reshape(np.asarray(route_xyz, float), (-1, 3))
    u, v = (p[:, 0] - xmin) / post - 0.5, (ymax - p[:, 1]) / post - 0.5  # column and row coordinates
    ok = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    u, v, z = u[ok], v[ok], p[ok, 2]
    i, j = np.minimum(np.floor(v), H - 2).astype(np.int64), np.minimum(np.floor(u), W - 2).astype(np.int64)
    keys, which = np.unique(np.column_stack([i // n * n, j // n * n]), axis=0, return_inverse=True)
    which = np.ravel(which)
    out = {}
    for k, (r0, c0) in enumerate(keys.tolist()):
        sel = which == k
        out[(r0, c0)] = (i[sel], j[sel], u[sel] - j[sel], v[sel] - i[sel], z[sel])
    return out


def _measure(z: np.ndarray, pts, r_first: int, c_first: int, base_height_m: float, acc: dict) -> None:
    """Add the route points ``pts`` (see :func:`_route_cells`) of one block to ``acc``: ``z`` holds
    the posts from row ``r_first`` and column ``c_first`` on (the block and its margin); points
    whose cell has a NaN post are left out."""
    i, j, fu, fv, zt = pts
    a, b = i - r_first, j - c_first
    zz = z.astype(float)
    top = zz[a, b] + fu * (zz[a, b + 1] - zz[a, b])
    bottom = zz[a + 1, b] + fu * (zz[a + 1, b + 1] - zz[a + 1, b])
    err = top + fv * (bottom - top) + base_height_m - zt
    err = err[np.isfinite(err)]
    acc["n"] += len(err)
    acc["sum"] += float(err.sum())
    acc["sum2"] += float(np.sum(err**2))
