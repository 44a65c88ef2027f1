"""Orbital products of a tiled world, written tile by tile over the route's coverage.

Coverage: the world tiles within ``tiled.orbital.corridor_m`` of the driven path. Products:
- ``orbital.tif``: the shaded nadir image (:mod:`sim.tiled.render`) at ``sensors.orbital.gsd_m``,
  a tiled (512 px) deflate-compressed GeoTIFF over the coverage's bounding box (image tiles
  outside the coverage are black), with ModelPixelScale / ModelTiepoint (pixel-is-area; the
  upper-left corner of pixel (0, 0) is (xmin, ymax)) in a user-defined metric CRS that is the
  simulator's world frame; ``orbital.tfw`` is its world file (pixel centres);
- ``orbital.png``: an overview (at most ``OVERVIEW_PX`` a side) over the same box, the image
  ``fgslam run/compare`` show (``orbital_extent`` / ``orbital_gsd_m`` in world.yaml);
- ``catalog.csv`` (``x,y,size,score``): the rock catalog of the detector ``sensors.orbital``
  (rocks under ``min_size_px`` never found; recall over the detectable rocks), and
  ``catalog_truth.csv`` (the true rock id of each entry, -1 for a false positive);
- ``craters.csv`` (``x,y,size,score``, size = rim diameter): the crater catalog of a detector
  whose probability depends on the diameter in pixels and the degradation (parameters in
  :class:`sim.tiled.config.OrbitalProductsConfig`), and ``craters_true.csv``: every crater of
  the world (id, centre, diameter, depth, rim height, degradation, blocky);
- ``dem.tif``: the terrain model of a stereo DTM over the same coverage (:mod:`sim.tiled.dem`);
- ``rocks_true.csv``: the rocks within stereo range of the path and the orbitally detectable rocks
  of the coverage (the rest are regenerated from the seed by :class:`TiledWorld`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from sim.config import SimConfig
from sim.craters import blocky
from sim.render.config import Appearance, Lighting
from sim.sensors.orbital import detection_curve
from sim.tiled.render import OrbitalRenderer
from sim.tiled.world import TiledWorld

OVERVIEW_PX = 4096
GEO_KEYS = (1, 1, 0, 4, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32767, 3076, 0, 1, 9001)


@dataclass
class OrbitalProducts:
    """What :func:`write_orbital_products` wrote: paths, coverage and counts."""

    paths: dict[str, Path] = field(default_factory=dict)
    image_extent: tuple[float, float, float, float] | None = None
    image_shape: tuple[int, int] | None = None
    overview_gsd_m: float | None = None
    counts: dict[str, int] = field(default_factory=dict)
    coverage: list[tuple[int, int]] = field(default_factory=list)  # the world tiles covered
    dem: dict | None = None  # the terrain model's description (sim.tiled.dem.write_dem)


def coverage_tiles(world: TiledWorld, path_xy: np.ndarray, corridor_m: float) -> list[tuple[int, int]]:
    """Tiles within ``corridor_m`` of the path ``path_xy`` (N, 2), sorted."""
    T = world.cfg.tile_size_m
    pts = np.reshape(path_xy, (-1, 2))[:: max(int(T / 8), 1)]
    if len(pts) == 0:
        return []
    r = corridor_m + T * math.sqrt(0.5)  # tile centre within this of a path point
    tree = cKDTree(pts)
    lo = np.floor((pts.min(axis=0) - corridor_m) / T).astype(int)
    hi = np.floor((pts.max(axis=0) + corridor_m) / T).astype(int)
    ix, iy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    centres = np.column_stack([(ix.ravel() + 0.5) * T, (iy.ravel() + 0.5) * T])
    d, _ = tree.query(centres, distance_upper_bound=r)
    keep = np.isfinite(d)
    return sorted(zip(ix.ravel()[keep].tolist(), iy.ravel()[keep].tolist()))


def _write_csv_rows(f, rows: np.ndarray, fmt: str) -> None:
    if len(rows):
        np.savetxt(f, rows, delimiter=",", fmt=fmt)


def write_orbital_products(world: TiledWorld, path_xy: np.ndarray, cfg: SimConfig, out: Path,
                           progress=None, route_xyz: np.ndarray | None = None) -> OrbitalProducts:
    """Write the products of the module doc for the driven path ``path_xy`` (N, 2) into ``out``.
    ``route_xyz`` (M, 3), the true base_link positions along it (optional): the terrain model's
    height error on the route is measured against them (``dem["route_height_rmse_m"]``)."""
    out = Path(out)
    oc, det = cfg.tiled.orbital, cfg.sensors.orbital
    tiles = coverage_tiles(world, path_xy, oc.corridor_m)
    res = OrbitalProducts(coverage=tiles)
    rng = np.random.default_rng([cfg.seed, 300])
    sample = world.rock_model.sample(200_000, np.random.default_rng([cfg.seed, 301]))
    p_rock = detection_curve(sample, det)
    path_tree = cKDTree(np.reshape(path_xy, (-1, 2)))
    stereo_reach = cfg.sensors.stereo.max_range_m + 2.0
    min_orbital_m = det.min_size_px * det.gsd_m
    names = ("catalog.csv", "catalog_truth.csv", "craters.csv", "rocks_true.csv")
    files = {n: open(out / n, "w") for n in names}
    try:
        files["catalog.csv"].write("x,y,size,score\n")
        files["catalog_truth.csv"].write("rock_id\n")
        files["craters.csv"].write("x,y,size,score\n")
        files["rocks_true.csv"].write("id,x,y,z,size,height,ejecta\n")
        counts = dict.fromkeys(("catalog", "catalog_true", "craters", "craters_true_in_coverage", "rocks_true"), 0)
        for k, (ix, iy) in enumerate(tiles):
            tile = world.tile(ix, iy)
            r = tile.rocks
            near = path_tree.query(r.xy_m, distance_upper_bound=stereo_reach)[0] < np.inf
            keep = near | (r.diameter_m >= min_orbital_m)
            _write_csv_rows(files["rocks_true.csv"], np.column_stack([r.id[keep], r.xyz_m[keep], r.diameter_m[keep],
                            r.height_m[keep], r.ejecta[keep]]), "%d,%.4f,%.4f,%.4f,%.4f,%.4f,%d")
            counts["rocks_true"] += int(keep.sum())
            cat, truth = _rock_catalog(r, p_rock(r.diameter_m), tile.extent, det, rng)
            _write_csv_rows(files["catalog.csv"], cat, "%.4f")
            _write_csv_rows(files["catalog_truth.csv"], truth[:, None], "%d")
            counts["catalog"] += len(cat)
            counts["catalog_true"] += int(np.sum(truth >= 0))
            craters = world.craters_in(tile.extent)
            counts["craters_true_in_coverage"] += len(craters)
            ccat = _crater_catalog(craters, tile.extent, det.gsd_m, oc, rng)
            _write_csv_rows(files["craters.csv"], ccat, "%.4f")
            counts["craters"] += len(ccat)
            if progress is not None:
                progress("catalogs", k + 1, len(tiles))
    finally:
        for f in files.values():
            f.close()
    res.counts = counts
    res.paths = {n: out / n for n in names}
    res.counts["craters_true"] = write_crater_truth(world, out / "craters_true.csv")
    res.paths["craters_true.csv"] = out / "craters_true.csv"
    if oc.write_image:
        _write_image(world, tiles, cfg, out, res, progress)
    if oc.write_dem and tiles:
        from sim.tiled.dem import write_dem

        res.dem = write_dem(world, tiles, oc, cfg.seed, out, progress, route_xyz=route_xyz,
                            base_height_m=cfg.rover.base_height_m)
        res.paths["dem.tif"] = out / "dem.tif"
        res.counts["dem_posts"] = res.dem["valid_posts"]
    res.counts["coverage_tiles"] = len(tiles)
    return res


def _rock_catalog(r, p: np.ndarray, extent, det, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Catalog rows (M, 4) x, y, size, score of one tile and the true rock id of each (-1: false)."""
    found = np.flatnonzero(rng.random(len(r)) < p)
    sigma = det.gsd_m * det.sigma_position_px
    xy = r.xy_m[found] + sigma * rng.standard_normal((len(found), 2))
    size = r.diameter_m[found] * np.exp(det.size_sigma_rel * rng.standard_normal(len(found)))
    score = rng.beta(6.0, 3.0, len(found))
    n_fp = int(rng.poisson(len(found) * (1.0 - det.precision) / det.precision)) if det.precision < 1.0 else 0
    x0, x1, y0, y1 = extent
    fp_xy = np.column_stack([rng.uniform(x0, x1, n_fp), rng.uniform(y0, y1, n_fp)])
    pool = r.diameter_m[found] if len(found) else np.array([det.min_size_px * det.gsd_m * 1.2])
    fp_size = rng.choice(pool, n_fp) * np.exp(0.3 * rng.standard_normal(n_fp))
    rows = np.column_stack([np.vstack([xy, fp_xy]), np.maximum(np.concatenate([size, fp_size]), 1e-3),
                            np.concatenate([score, rng.beta(3.0, 4.0, n_fp)])])
    truth = np.concatenate([r.id[found], np.full(n_fp, -1, dtype=np.int64)])
    order = rng.permutation(len(rows))
    return rows[order], truth[order]


def crater_detection_probability(diameter_m: np.ndarray, degradation: np.ndarray, gsd_m: float, oc) -> np.ndarray:
    """p = recall_max sigmoid((ln D_px - ln d50_px) / log_width) (1 - penalty g), 0 below min_px."""
    d_px = np.asarray(diameter_m, dtype=float) / gsd_m
    p = oc.crater_recall_max / (1.0 + np.exp(-(np.log(np.maximum(d_px, 1e-9)) - math.log(oc.crater_d50_px)) / oc.crater_log_width))
    p = p * (1.0 - oc.crater_degradation_penalty * np.asarray(degradation, dtype=float))
    return np.where(d_px >= oc.crater_min_px, p, 0.0)


def _crater_catalog(c, extent, gsd_m: float, oc, rng: np.random.Generator) -> np.ndarray:
    """Crater catalog rows (M, 4) x, y, size (rim diameter), score of one tile."""
    p = crater_detection_probability(c.diameter_m, c.degradation, gsd_m, oc)
    found = np.flatnonzero(rng.random(len(c)) < p)
    d = c.diameter_m[found]
    sigma = oc.crater_sigma_centre_rel * d + 0.5 * gsd_m
    xy = c.xy_m[found] + sigma[:, None] * rng.standard_normal((len(found), 2))
    size = d * np.exp(oc.crater_sigma_size_rel * rng.standard_normal(len(found)))
    score = rng.beta(8.0, 2.0, len(found))
    n_fp = int(rng.poisson(len(found) * (1.0 - oc.crater_precision) / oc.crater_precision)) if oc.crater_precision < 1 else 0
    x0, x1, y0, y1 = extent
    fp_xy = np.column_stack([rng.uniform(x0, x1, n_fp), rng.uniform(y0, y1, n_fp)])
    pool = d if len(d) else np.array([oc.crater_d50_px * gsd_m])
    fp_size = rng.choice(pool, n_fp) * np.exp(0.3 * rng.standard_normal(n_fp))
    rows = np.column_stack([np.vstack([xy, fp_xy]), np.concatenate([size, fp_size]),
                            np.concatenate([score, rng.beta(3.0, 4.0, n_fp)])])
    return rows[rng.permutation(len(rows))]


def write_crater_truth(world: TiledWorld, path: Path) -> int:
    """Every crater with its centre in the world (cell by cell, nothing kept); returns the count."""
    xmin, xmax, ymin, ymax = world.extent
    n = 0
    with open(path, "w") as f:
        f.write("id,x,y,diameter,depth,rim_height,degradation,blocky\n")
        for k, _lo, _hi, cell in world._classes():
            for cx in range(math.floor(xmin / cell), math.floor(xmax / cell) + 1):
                for cy in range(math.floor(ymin / cell), math.floor(ymax / cell) + 1):
                    c = world._make_cell((k, cx, cy))
                    x, y = c.xy_m[:, 0], c.xy_m[:, 1]
                    c = c.subset((x >= xmin) & (x < xmax) & (y >= ymin) & (y < ymax))
                    rows = np.column_stack([c.id, c.xy_m, c.diameter_m, c.depth_m, c.rim_height_m, c.degradation,
                                            blocky(c, world.cfg.ejecta)])
                    _write_csv_rows(f, rows, "%d,%.3f,%.3f,%.3f,%.4f,%.4f,%.4f,%d")
                    n += len(c)
    return n


def _write_image(world: TiledWorld, tiles, cfg: SimConfig, out: Path, res: OrbitalProducts, progress) -> None:
    import cv2
    import tifffile

    oc, gsd = cfg.tiled.orbital, cfg.sensors.orbital.gsd_m
    px = oc.image_tile_px
    side = px * gsd  # image tile, metres
    if not tiles:
        return
    T = world.cfg.tile_size_m
    xs = [ix * T for ix, _ in tiles] + [(ix + 1) * T for ix, _ in tiles]
    ys = [iy * T for _, iy in tiles] + [(iy + 1) * T for _, iy in tiles]
    c0, c1 = math.floor(min(xs) / side), math.ceil(max(xs) / side)
    r0, r1 = math.floor(min(ys) / side), math.ceil(max(ys) / side)
    ext = (c0 * side, c1 * side, r0 * side, r1 * side)
    W, H = (c1 - c0) * px, (r1 - r0) * px
    covered = set(tiles)
    renderer = OrbitalRenderer(world, gsd, Lighting(oc.sun_elevation_deg, oc.sun_azimuth_deg), Appearance(seed=cfg.seed),
                               min_rock_px=oc.render_min_rock_px)
    f = 1
    while max(W, H) / f > OVERVIEW_PX and f < px:
        f *= 2
    overview = np.zeros((H // f, W // f), np.uint8)
    jobs = [(r, c) for r in range(r1 - 1, r0 - 1, -1) for c in range(c0, c1)]  # row-major from the top

    def tiles_iter():
        for k, (r, c) in enumerate(jobs):
            e = (c * side, (c + 1) * side, r * side, (r + 1) * side)
            if any(t in covered for t in world.tiles_overlapping(e)):
                img = renderer.tile(e, np.random.default_rng([cfg.seed, 302, r + (1 << 20), c + (1 << 20)])).image
                i, j = (r1 - 1 - r) * px // f, (c - c0) * px // f
                overview[i:i + px // f, j:j + px // f] = cv2.resize(img, (px // f, px // f), interpolation=cv2.INTER_AREA)
            else:
                img = np.zeros((px, px), np.uint8)
            if progress is not None:
                progress("image", k + 1, len(jobs))
            yield img

    geo = [(33550, "d", 3, (gsd, gsd, 0.0), False), (33922, "d", 6, (0.0, 0.0, 0.0, ext[0], ext[3], 0.0), False),
           (34735, "H", len(GEO_KEYS), GEO_KEYS, False)]
    tifffile.imwrite(out / "orbital.tif", tiles_iter(), shape=(H, W), dtype=np.uint8, tile=(px, px),
                     compression="zlib", photometric="minisblack", extratags=geo, bigtiff=H * W > 2**31,
                     description=f"fgslam sim {world.name} seed {cfg.seed}: nadir image, {gsd} m/px, world frame (ENU m)")
    (out / "orbital.tfw").write_text("\n".join(f"{v:.6f}" for v in (gsd, 0.0, 0.0, -gsd, ext[0] + gsd / 2, ext[3] - gsd / 2)) + "\n")
    if not cv2.imwrite(str(out / "orbital.png"), overview):
        raise OSError(f"cannot write {out / 'orbital.png'}")
    res.paths.update({"orbital.tif": out / "orbital.tif", "orbital.tfw": out / "orbital.tfw", "orbital.png": out / "orbital.png"})
    res.image_extent, res.image_shape, res.overview_gsd_m = ext, (H, W), gsd * f
