"""The part of the orbital map a recording shows: square tiles of the orbital image along the path.

A recording of a kilometre traverse must grow with the path, not with the world (issue budget:
under 5 MB per km). The orbital image is therefore cut into square tiles of ``tile_px`` pixels
and only the tiles within ``margin_m`` of the path are kept, at one ground resolution chosen so
that all kept tiles together hold at most ``budget_px`` pixels (never finer than the image's
own). Catalog entries are kept where their tile is kept, so the image and the catalogs show the
same ground. Pure arrays in, arrays out (no I/O, no rerun).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# what a recording shows of the orbital image (see module doc)
MARGIN_M = 30.0  # ground kept either side of the path
TILE_PX = 64  # tile side in pixels (small tiles follow the path closely)
IMAGE_PX_PER_M = 300  # pixel budget per metre of path (RGB: 0.9 MB per km) ...
MIN_IMAGE_PX = 512 * 512  # ... but at least this (a short drive still shows its surroundings)
MAX_IMAGE_PX = 1024 * 1024  # ... and at most this (the whole image of a yard)


@dataclass(frozen=True)
class Tile:
    """One tile: ``image`` (h, w, 3) uint8 covering ``extent`` (xmin, xmax, ymin, ymax) metres,
    its first row at ymax (north up, as the orbital image)."""

    extent: tuple[float, float, float, float]
    image: np.ndarray


@dataclass(frozen=True)
class MapTiles:
    """The tiles kept and the grid they were cut on (to test which tile a point falls in)."""

    tiles: list[Tile]
    gsd_m: float  # ground resolution of the tiles
    side_m: float  # tile side on the ground
    origin_xy: tuple[float, float]  # grid origin: the image's (xmin, ymax) corner
    kept: frozenset  # (col, row) indices of the kept tiles

    def covers(self, xy: np.ndarray) -> np.ndarray:
        """Mask (N,) of the points ``xy`` (N, 2) that fall inside a kept tile."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        c = np.floor((xy[:, 0] - self.origin_xy[0]) / self.side_m).astype(np.int64)
        r = np.floor((self.origin_xy[1] - xy[:, 1]) / self.side_m).astype(np.int64)
        return np.array([(int(i), int(j)) in self.kept for i, j in zip(c, r)], dtype=bool)


def path_length_m(path_xy: np.ndarray) -> float:
    p = np.asarray(path_xy, dtype=float).reshape(-1, 2)
    p = p[np.all(np.isfinite(p), axis=1)]
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0


def pixel_budget(path_xy: np.ndarray | None) -> int:
    """Pixels a recording may spend on the orbital image for a path ``path_xy`` (N, 2)."""
    if path_xy is None:
        return MAX_IMAGE_PX
    return int(min(MAX_IMAGE_PX, max(MIN_IMAGE_PX, IMAGE_PX_PER_M * path_length_m(path_xy))))


def _near_path(centers: np.ndarray, path_xy: np.ndarray, reach_m: float) -> np.ndarray:
    from scipy.spatial import cKDTree

    d, _ = cKDTree(path_xy).query(centers, distance_upper_bound=reach_m)
    return np.isfinite(d)


def _densified(path_xy: np.ndarray, step_m: float) -> np.ndarray:
    """``path_xy`` with points added so that consecutive points are at most ``step_m`` apart."""
    p = np.asarray(path_xy, dtype=float).reshape(-1, 2)
    if len(p) < 2:
        return p
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    n = np.maximum(1, np.ceil(seg / step_m).astype(int))
    parts = [p[i] + np.outer(np.arange(n[i]) / n[i], p[i + 1] - p[i]) for i in range(len(seg))]
    return np.vstack(parts + [p[-1:]])


def _grid(extent, gsd_m: float, tile_px: int):
    x0, x1, y0, y1 = extent
    side = tile_px * gsd_m
    nc, nr = max(1, int(np.ceil((x1 - x0) / side))), max(1, int(np.ceil((y1 - y0) / side)))
    return side, nc, nr


def _kept(extent, gsd_m: float, tile_px: int, path_xy: np.ndarray, margin_m: float) -> tuple[float, list]:
    """Tile side and the (col, row) of every tile within ``margin_m`` of the path at ``gsd_m``."""
    x0, _, _, y1 = extent
    side, nc, nr = _grid(extent, gsd_m, tile_px)
    cc, rr = np.meshgrid(np.arange(nc), np.arange(nr), indexing="ij")
    centers = np.column_stack([x0 + (cc.ravel() + 0.5) * side, y1 - (rr.ravel() + 0.5) * side])
    # a tile is near when some path point lies within margin of its square (the half diagonal
    # bounds the distance from the centre to the square's edge: a superset by at most 0.41 side)
    path = _densified(path_xy, 0.25 * side)
    near = _near_path(centers, path, margin_m + side / np.sqrt(2.0))
    return side, [(int(c), int(r)) for c, r in zip(cc.ravel()[near], rr.ravel()[near])]


def map_tiles(image: np.ndarray, extent, path_xy: np.ndarray | None, *, margin_m: float = MARGIN_M,
              tile_px: int = TILE_PX, budget_px: int | None = None) -> MapTiles:
    """The tiles of ``image`` (H, W, 3) covering ``extent`` (xmin, xmax, ymin, ymax) that a
    recording of ``path_xy`` (N, 2) shows (see module doc). Without a path: the whole image as
    one tile of at most ``budget_px`` pixels (default :func:`pixel_budget`)."""
    import cv2

    image = np.asarray(image)
    H, W = image.shape[:2]
    x0, x1, y0, y1 = (float(v) for v in extent)
    gx, gy = (x1 - x0) / W, (y1 - y0) / H
    native = max(gx, gy)
    budget = int(budget_px if budget_px is not None else pixel_budget(path_xy))
    path = None if path_xy is None else np.asarray(path_xy, dtype=float).reshape(-1, 2)
    if path is not None:
        path = path[np.all(np.isfinite(path), axis=1)]
    if path is None or not len(path):
        gsd = max(native, 1.002 * np.sqrt((x1 - x0) * (y1 - y0) / budget))  # (pixel rounding)
        px = max(1, int(np.ceil(max(x1 - x0, y1 - y0) / gsd)))
        return _cut(image, (x0, x1, y0, y1), gsd, px, [(0, 0)], cv2)
    gsd = native
    for _ in range(40):  # coarsen until the kept tiles fit the budget
        side, kept = _kept((x0, x1, y0, y1), gsd, tile_px, path, margin_m)
        if len(kept) * tile_px * tile_px <= budget or side >= max(x1 - x0, y1 - y0):
            break
        gsd *= max(1.05, np.sqrt(len(kept) * tile_px * tile_px / budget))
    return _cut(image, (x0, x1, y0, y1), gsd, tile_px, kept, cv2)


def _cut(image: np.ndarray, extent, gsd: float, tile_px: int, kept: list, cv2) -> MapTiles:
    H, W = image.shape[:2]
    x0, x1, y0, y1 = extent
    gx, gy = (x1 - x0) / W, (y1 - y0) / H
    side = tile_px * gsd
    tiles = []
    for c, r in kept:
        # the image pixels under the tile, clipped to the image; the tile's extent is theirs
        c0, c1 = int(np.floor(c * side / gx)), int(np.ceil((c + 1) * side / gx))
        r0, r1 = int(np.floor(r * side / gy)), int(np.ceil((r + 1) * side / gy))
        c0, c1, r0, r1 = max(c0, 0), min(c1, W), max(r0, 0), min(r1, H)
        if c1 <= c0 or r1 <= r0:
            continue
        crop = image[r0:r1, c0:c1, :3]
        w = max(1, min(tile_px, int(round((c1 - c0) * gx / gsd))))
        h = max(1, min(tile_px, int(round((r1 - r0) * gy / gsd))))
        if (h, w) != crop.shape[:2]:
            crop = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA)
        tiles.append(Tile((x0 + c0 * gx, x0 + c1 * gx, y1 - r1 * gy, y1 - r0 * gy), np.ascontiguousarray(crop)))
    return MapTiles(tiles, float(gsd), float(side), (float(x0), float(y1)), frozenset(kept))
