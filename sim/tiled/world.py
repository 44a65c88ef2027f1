"""A kilometre-scale world generated lazily: tiles of terrain and rocks, cells of craters, each a
pure function of (world seed, index), held in bounded LRU caches so that memory does not grow
with the area driven or imaged.

Craters live in cells of three size classes (1-8 m in 64 m cells, 8-40 m in 256 m cells, 40 m and
more in 1024 m cells), so a tile asks only the few cells whose craters can reach it (a crater's
relief reaches 4 radii, its ejecta 3). Queries by region: :meth:`TiledWorld.heightmap`,
:meth:`craters_in` / :meth:`craters_near` (the crater truth, for any sensor), :meth:`rocks_in`,
:meth:`local_world` (a :class:`sim.world.World` of a window, for the stereo model and renderer)
and :meth:`coarse_heightmap` (the coarse global DEM: large-scale terrain and craters of 32 m and
more at ``coarse_resolution_m``, for route planning).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sim.craters import (
    INFLUENCE_RADIUS,
    Craters,
    CraterSFD,
    blocky,
    crater_relief,
    ejecta_blocks,
    sample_craters,
    stamp_relief,
)
from sim.errors import SimError
from sim.rock_sfd import GolombekRapp
from sim.rocks import Rocks
from sim.terrain import Heightmap
from sim.tiled.config import TiledWorldConfig
from sim.tiled.noise import FractalNoise
from sim.tiled.tiles import Tile, TileRocks, tile_dem, tile_meshes, tile_rock_set, tile_rocks
from sim.world import World

CRATER_CLASSES = ((8.0, 64.0), (40.0, 256.0), (math.inf, 1024.0))  # (upper diameter m, cell m)
_CELL_OFFSET = 1 << 15  # crater id = class (2 bits) | cell x, y (16 bits each) | row (18 bits): < 2^52


class LRUCache:
    """At most ``maxsize`` values made by ``factory(key)``; ``made`` counts factory calls."""

    def __init__(self, maxsize: int, factory: Callable) -> None:
        if maxsize < 1:
            raise SimError(f"cache size must be >= 1, got {maxsize}")
        self.maxsize, self.factory, self._d, self.made = maxsize, factory, OrderedDict(), 0

    def __call__(self, key):
        d = self._d
        if key in d:
            d.move_to_end(key)
            return d[key]
        value = self.factory(key)
        self.made += 1
        d[key] = value
        if len(d) > self.maxsize:
            d.popitem(last=False)
        return value

    def get(self, key, make: Callable):
        """The value of ``key``, made by ``make()`` (instead of the factory) when missing."""
        d = self._d
        if key in d:
            d.move_to_end(key)
            return d[key]
        value = make()
        self.made += 1
        d[key] = value
        if len(d) > self.maxsize:
            d.popitem(last=False)
        return value

    def __len__(self) -> int:
        return len(self._d)


@dataclass
class LocalWindow:
    """A window of the world as a yard-like :class:`sim.world.World` (terrain + rock meshes);
    ``shape_error`` (R,) is each rock's standard-normal stereo centre-error draw."""

    world: World
    shape_error: np.ndarray


class TiledWorld:
    """The world of ``cfg`` (a resolved :class:`TiledWorldConfig`: no ``None`` left) for ``seed``."""

    def __init__(self, name: str, seed: int, cfg: TiledWorldConfig) -> None:
        for what, v in (("size_m", cfg.size_m), ("terrain.relief_m", cfg.terrain.relief_m), ("terrain.hurst", cfg.terrain.hurst),
                        ("rocks.k", cfg.rocks.k), ("craters.age_gyr", cfg.craters.age_gyr)):
            if v is None:
                raise SimError(f"tiled world {name}: tiled.{what} is not set (use sim.tiled.preset_config)")
        if not (cfg.tile_size_m > 0 and cfg.resolution_m > 0 and
                abs(cfg.tile_size_m / cfg.resolution_m - round(cfg.tile_size_m / cfg.resolution_m)) < 1e-9):
            raise SimError(f"tiled.tile_size_m ({cfg.tile_size_m}) must be a positive multiple of resolution_m ({cfg.resolution_m})")
        self.name, self.seed, self.cfg = name, int(seed), cfg
        half = 0.5 * cfg.size_m
        self.extent = (-half, half, -half, half)
        t = cfg.terrain
        self.noise = FractalNoise(self.seed, t.relief_m, t.largest_scale_m, t.smallest_scale_m, t.hurst)
        c = cfg.craters
        self.sfd = CraterSFD(c.age_gyr, c.production, c.equilibrium, c.min_diameter_m, c.max_diameter_m, c.density_scale)
        self.rock_model = GolombekRapp(cfg.rocks.k, cfg.rocks.min_diameter_m, cfg.rocks.max_diameter_m)
        self._cells = LRUCache(8192, self._make_cell)
        self._tiles = LRUCache(cfg.cache_tiles, self._make_tile)
        self._meshes = LRUCache(6, self._make_meshes)
        self._blocks = LRUCache(1024, lambda key: None)  # crater id -> its ejecta blocks (filled by get)
        self._coarse = LRUCache(4, self._make_coarse)

    # -- craters -------------------------------------------------------------------------------
    def _classes(self) -> list[tuple[int, float, float, float]]:
        """(class index, lower diameter, upper diameter, cell size) of the crater classes in use."""
        out, lo = [], self.sfd.d_min_m
        for k, (hi, cell) in enumerate(CRATER_CLASSES):
            hi = min(hi, self.sfd.d_max_m)
            if hi > lo:
                out.append((k, lo, hi, cell))
            lo = max(lo, hi)
        return out

    def _make_cell(self, key) -> Craters:
        k, cx, cy = key
        _, lo, hi, cell = next(c for c in self._classes() if c[0] == k)
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 0xC2A7E2, k, cx + _CELL_OFFSET, cy + _CELL_OFFSET])
        ids = (k << 50) | ((cx + _CELL_OFFSET) << 34) | ((cy + _CELL_OFFSET) << 18)
        return sample_craters(self.sfd, (cx * cell, (cx + 1) * cell, cy * cell, (cy + 1) * cell), rng,
                              d_lo_m=lo, d_hi_m=hi, id_base=ids)

    def craters_near(self, extent: tuple[float, float, float, float], reach_radii: float = INFLUENCE_RADIUS,
                     d_min_m: float = 0.0) -> Craters:
        """Craters of diameter >= ``d_min_m`` whose disc of ``reach_radii`` radii meets ``extent``."""
        xmin, xmax, ymin, ymax = extent
        parts = []
        for k, _lo, hi, cell in self._classes():
            if hi <= d_min_m:
                continue
            r = reach_radii * 0.5 * hi
            for cx in range(math.floor((xmin - r) / cell), math.floor((xmax + r) / cell) + 1):
                for cy in range(math.floor((ymin - r) / cell), math.floor((ymax + r) / cell) + 1):
                    parts.append(self._cells((k, cx, cy)))
        c = Craters.concat(parts)
        if d_min_m > 0:
            c = c.subset(c.diameter_m >= d_min_m)
        return c.reaching(extent, reach_radii)

    def craters_in(self, extent: tuple[float, float, float, float]) -> Craters:
        """Craters whose centre lies in ``extent`` [xmin, xmax) x [ymin, ymax) (the truth of a region)."""
        c = self.craters_near(extent, reach_radii=0.0)
        xmin, xmax, ymin, ymax = extent
        x, y = c.xy_m[:, 0], c.xy_m[:, 1]
        return c.subset((x >= xmin) & (x < xmax) & (y >= ymin) & (y < ymax))

    def _blocks_of(self, craters: Craters) -> tuple[np.ndarray, np.ndarray]:
        """Positions (M, 2) and diameters (M,) of the ejecta blocks of ``craters`` (cached per crater)."""
        out_xy, out_d = [], []
        for k in range(len(craters)):
            b = self._blocks.get(int(craters.id[k]), lambda k=k: ejecta_blocks(craters.subset([k]), self.seed, self.cfg.ejecta))
            out_xy.append(b.xy_m)
            out_d.append(b.diameter_m)
        if not out_xy:
            return np.zeros((0, 2)), np.zeros(0)
        return np.vstack(out_xy), np.concatenate(out_d)

    # -- tiles ---------------------------------------------------------------------------------
    def tile_index(self, x: float) -> int:
        return math.floor(x / self.cfg.tile_size_m)

    def tile_extent(self, ix: int, iy: int) -> tuple[float, float, float, float]:
        T = self.cfg.tile_size_m
        return (ix * T, (ix + 1) * T, iy * T, (iy + 1) * T)

    def tiles_overlapping(self, extent: tuple[float, float, float, float]) -> list[tuple[int, int]]:
        xmin, xmax, ymin, ymax = extent
        T = self.cfg.tile_size_m
        return [(ix, iy) for iy in range(math.floor(ymin / T), math.ceil(ymax / T))
                for ix in range(math.floor(xmin / T), math.ceil(xmax / T))]

    def tile(self, ix: int, iy: int) -> Tile:
        """Tile (ix, iy) (cached; generated from (seed, ix, iy) alone)."""
        return self._tiles((ix, iy))

    @property
    def tiles_made(self) -> int:
        return self._tiles.made

    def _make_tile(self, key) -> Tile:
        ix, iy = key
        cfg = self.cfg
        ext = self.tile_extent(ix, iy)
        m = cfg.tile_margin_m
        ext_dem = (ext[0] - m, ext[1] + m, ext[2] - m, ext[3] + m)
        craters = self.craters_near(ext_dem)
        terrain = tile_dem(self.noise, craters, ext_dem, cfg.resolution_m)
        fresh = self.craters_near(ext, reach_radii=cfg.ejecta.outer_radius, d_min_m=cfg.ejecta.min_crater_diameter_m)
        bxy, bd = self._blocks_of(fresh.subset(blocky(fresh, cfg.ejecta)))
        inside = ((bxy[:, 0] >= ext[0]) & (bxy[:, 0] < ext[1]) & (bxy[:, 1] >= ext[2]) & (bxy[:, 1] < ext[3])
                  & (bd >= cfg.rocks.min_diameter_m))
        rocks = tile_rocks(self.seed, ix, iy, ext, terrain, self.rock_model, bxy[inside], bd[inside],
                           cfg.rocks.embed_fraction)
        return Tile(ix, iy, ext, terrain, rocks, craters)

    def _make_meshes(self, key):
        return tile_meshes(self.seed, self.tile(*key))

    # -- region queries ------------------------------------------------------------------------
    def _lattice(self, extent) -> tuple[np.ndarray, np.ndarray]:
        res = self.cfg.resolution_m
        xmin, xmax, ymin, ymax = extent
        i0, i1 = math.floor(xmin / res), math.ceil(xmax / res)
        j0, j1 = math.floor(ymin / res), math.ceil(ymax / res)
        return res * np.arange(i0, i1 + 1), res * np.arange(j0, j1 + 1)

    def heightmap(self, extent: tuple[float, float, float, float]) -> Heightmap:
        """The fine DEM over ``extent`` (grown to the lattice), assembled from tiles."""
        xs, ys = self._lattice(extent)
        z = np.empty((len(ys), len(xs)))
        res = self.cfg.resolution_m
        for ix, iy in self.tiles_overlapping((xs[0], xs[-1] + 1e-9, ys[0], ys[-1] + 1e-9)):
            t = self.tile(ix, iy)
            tx0, _, ty0, _ = t.terrain.extent
            cx = np.flatnonzero((xs >= t.extent[0] - 1e-9) & (xs <= t.extent[1] + 1e-9))
            cy = np.flatnonzero((ys >= t.extent[2] - 1e-9) & (ys <= t.extent[3] + 1e-9))
            if len(cx) == 0 or len(cy) == 0:
                continue
            jx = np.rint((xs[cx] - tx0) / res).astype(int)
            jy = np.rint((ys[cy] - ty0) / res).astype(int)
            z[np.ix_(cy, cx)] = t.terrain.z_m[np.ix_(jy, jx)]
        return Heightmap(z, (xs[0], xs[-1], ys[0], ys[-1]))

    def rocks_in(self, extent: tuple[float, float, float, float], min_diameter_m: float = 0.0) -> TileRocks:
        """The rocks (no meshes) whose centre lies in ``extent`` with diameter >= ``min_diameter_m``."""
        parts = []
        for ix, iy in self.tiles_overlapping(extent):
            r = self.tile(ix, iy).rocks
            parts.append(_select(r, _in_box(r.xy_m, extent) & (r.diameter_m >= min_diameter_m)))
        return _concat_rocks(parts)

    def rock_meshes_in(self, extent: tuple[float, float, float, float], min_diameter_m: float = 0.0
                       ) -> tuple[Rocks, np.ndarray]:
        """:class:`sim.rocks.Rocks` (with meshes) whose centre lies in ``extent``, and their
        ``shape_error`` draws (R,)."""
        parts, shape = [], []
        for ix, iy in self.tiles_overlapping(extent):
            t = self.tile(ix, iy)
            keep = np.flatnonzero(_in_box(t.rocks.xy_m, extent) & (t.rocks.diameter_m >= min_diameter_m))
            if len(keep):
                v, f = self._meshes((ix, iy))
                parts.append(tile_rock_set(t, v, f, keep))
                shape.append(t.rocks.shape_error[keep])
        rocks = Rocks.concat(parts)
        return rocks, (np.concatenate(shape) if shape else np.zeros(0))

    def local_world(self, extent: tuple[float, float, float, float], rock_margin_m: float = 1.5) -> LocalWindow:
        """Terrain of ``extent`` and the rocks whose centre lies within ``rock_margin_m`` of it."""
        xmin, xmax, ymin, ymax = extent
        terrain = self.heightmap(extent)
        m = rock_margin_m
        rocks, shape = self.rock_meshes_in((xmin - m, xmax + m, ymin - m, ymax + m))
        return LocalWindow(World(name=self.name, terrain=terrain, rocks=rocks, source="tiled"), shape)

    def height_at(self, xy_m: np.ndarray) -> np.ndarray:
        """Terrain height (N,) at scattered points (the DEM's function itself, not interpolated)."""
        xy = np.reshape(np.asarray(xy_m, dtype=float), (-1, 2))
        if len(xy) == 0:
            return np.zeros(0)
        ext = (xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max())
        c = self.craters_near(ext)
        return self.noise.at(xy) + crater_relief(xy, c.xy_m, c.diameter_m, c.degradation)

    # -- coarse global DEM -----------------------------------------------------------------------
    def _make_coarse(self, key) -> Heightmap:
        cx, cy = key
        C, res = self.cfg.coarse_tile_m, self.cfg.coarse_resolution_m
        ext = (cx * C, (cx + 1) * C, cy * C, (cy + 1) * C)
        xs = ext[0] + res * np.arange(round(C / res) + 1)
        ys = ext[2] + res * np.arange(round(C / res) + 1)
        z = self.noise.grid(xs, ys, min_spacing_m=2.0 * res)
        c = self.craters_near(ext, d_min_m=4.0 * res)
        z = stamp_relief(z, ext, c.xy_m, c.diameter_m, c.degradation)
        return Heightmap(z, ext)

    def coarse_heightmap(self, extent: tuple[float, float, float, float]) -> Heightmap:
        """The coarse DEM (large-scale terrain and craters >= 4 coarse cells) over ``extent``."""
        C, res = self.cfg.coarse_tile_m, self.cfg.coarse_resolution_m
        xmin, xmax, ymin, ymax = extent
        xs = res * np.arange(math.floor(xmin / res), math.ceil(xmax / res) + 1)
        ys = res * np.arange(math.floor(ymin / res), math.ceil(ymax / res) + 1)
        z = np.empty((len(ys), len(xs)))
        for cx in range(math.floor(xs[0] / C), math.floor(xs[-1] / C) + 1):
            for cy in range(math.floor(ys[0] / C), math.floor(ys[-1] / C) + 1):
                t = self._coarse((cx, cy))
                sx = np.flatnonzero((xs >= t.extent[0]) & (xs <= t.extent[1]))
                sy = np.flatnonzero((ys >= t.extent[2]) & (ys <= t.extent[3]))
                jx = np.rint((xs[sx] - t.extent[0]) / res).astype(int)
                jy = np.rint((ys[sy] - t.extent[2]) / res).astype(int)
                z[np.ix_(sy, sx)] = t.z_m[np.ix_(jy, jx)]
        return Heightmap(z, (xs[0], xs[-1], ys[0], ys[-1]))


def _in_box(xy: np.ndarray, extent) -> np.ndarray:
    xmin, xmax, ymin, ymax = extent
    return (xy[:, 0] >= xmin) & (xy[:, 0] < xmax) & (xy[:, 1] >= ymin) & (xy[:, 1] < ymax)


def _select(r: TileRocks, keep: np.ndarray) -> TileRocks:
    return TileRocks(*(getattr(r, f)[keep] for f in TileRocks.__dataclass_fields__))


def _concat_rocks(parts: list[TileRocks]) -> TileRocks:
    names = list(TileRocks.__dataclass_fields__)
    if not parts:
        empty = {"xy_m": (0, 2), "xyz_m": (0, 3), "semi_m": (0, 3)}
        return TileRocks(*(np.zeros(empty.get(n, (0,)), dtype=np.int64 if n == "id" else bool if n == "ejecta" else float)
                           for n in names))
    return TileRocks(*(np.concatenate([getattr(p, n) for p in parts]) for n in names))
