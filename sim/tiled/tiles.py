"""One tile of a kilometre-scale world: its fine DEM (fractal terrain plus every crater that
reaches it) and its rocks (Golombek & Rapp background plus the ejecta blocks of fresh craters
whose centres fall in the tile), all drawn from generators seeded by (world seed, tile index).

A tile's DEM spans the tile plus ``tile_margin_m`` on every side on the global lattice of
``resolution_m`` nodes (rock footprints near the edge rest on it); the tile owns the rocks whose
centre lies in [x0, x0 + T) x [y0, y0 + T).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.craters import Craters, stamp_relief
from sim.rocks import RockEllipsoids, Rocks, ellipsoid_meshes, rock_ellipsoids
from sim.terrain import Heightmap

ROCK_ID_K_BITS = 20  # rock id = (tile key << 20) | row: 1 M rocks per tile; ids < 2^52 (exact as float64)
_OFFSET = 1 << 15  # tile indices as non-negative ints in seeds and ids (|ix|, |iy| < 32768)


def tile_key_int(ix: int, iy: int) -> int:
    """A non-negative int below 2^32 naming tile (ix, iy)."""
    if not (-_OFFSET <= ix < _OFFSET and -_OFFSET <= iy < _OFFSET):
        raise ValueError(f"tile index ({ix}, {iy}) out of range")
    return ((ix + _OFFSET) << 16) | (iy + _OFFSET)


def tile_rng(seed: int, stream: int, ix: int, iy: int) -> np.random.Generator:
    """The generator of ``stream`` (terrain, rocks, meshes, ...) of tile (ix, iy)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, stream, ix + _OFFSET, iy + _OFFSET])


STREAM_ROCKS, STREAM_MESH, STREAM_SHAPE, STREAM_BUMPS = 0x40C5, 0x3E5A, 0x5A9E, 0xB0B5


@dataclass(frozen=True)
class TileRocks:
    """The rocks a tile owns: ``xy_m`` (R, 2), ``diameter_m`` (R,) (mean caliper width), ``id``
    (R,) int64, ``ejecta`` (R,) bool (thrown by a crater), ``shape_error`` (R,) a standard-normal
    draw per rock (its stereo centre error in units of ``centre_error_frac`` radii), and the
    ellipsoids the meshes perturb: centres ``xyz_m`` (R, 3) (the rocks' true centres),
    ``semi_m`` (R, 3), ``yaw_rad`` (R,)."""

    xy_m: np.ndarray
    diameter_m: np.ndarray
    id: np.ndarray
    ejecta: np.ndarray
    shape_error: np.ndarray
    xyz_m: np.ndarray
    semi_m: np.ndarray
    yaw_rad: np.ndarray

    def __len__(self) -> int:
        return len(self.diameter_m)

    @property
    def height_m(self) -> np.ndarray:
        return 2.0 * self.semi_m[:, 2]

    def ellipsoids(self) -> RockEllipsoids:
        return RockEllipsoids(self.xyz_m, self.semi_m, self.yaw_rad)


@dataclass(frozen=True)
class Tile:
    """Tile (ix, iy): ``terrain`` (its DEM with margin), ``rocks``, and ``craters`` (those that
    reach it, stamped into the DEM)."""

    ix: int
    iy: int
    extent: tuple[float, float, float, float]  # the tile proper (without margin)
    terrain: Heightmap
    rocks: TileRocks
    craters: Craters


def tile_dem(noise, craters: Craters, extent_dem: tuple[float, float, float, float], resolution_m: float) -> Heightmap:
    """Fractal terrain plus the relief of ``craters`` on the lattice nodes of ``extent_dem``."""
    xmin, xmax, ymin, ymax = extent_dem
    xs = xmin + resolution_m * np.arange(round((xmax - xmin) / resolution_m) + 1)
    ys = ymin + resolution_m * np.arange(round((ymax - ymin) / resolution_m) + 1)
    z = noise.grid(xs, ys)
    z = stamp_relief(z, (xs[0], xs[-1], ys[0], ys[-1]), craters.xy_m, craters.diameter_m, craters.degradation)
    return Heightmap(z, (xs[0], xs[-1], ys[0], ys[-1]))


def tile_rocks(seed: int, ix: int, iy: int, extent: tuple[float, float, float, float], terrain: Heightmap,
               background, blocks_xy: np.ndarray, blocks_d: np.ndarray, embed_fraction: float) -> TileRocks:
    """The tile's rocks: Poisson(area x density) background rocks of the Golombek & Rapp model
    ``background`` uniform over the tile, then the ejecta blocks given (centres in the tile)."""
    x0, x1, y0, y1 = extent
    rng = tile_rng(seed, STREAM_ROCKS, ix, iy)
    n = int(rng.poisson((x1 - x0) * (y1 - y0) * background.density_per_m2))
    d_bg = background.sample(n, rng)
    xy_bg = np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)])
    xy = np.vstack([xy_bg, np.reshape(blocks_xy, (-1, 2))])
    d = np.concatenate([d_bg, np.ravel(blocks_d)])
    shape_error = tile_rng(seed, STREAM_SHAPE, ix, iy).standard_normal(len(d))
    ell = rock_ellipsoids(xy, d, tile_rng(seed, STREAM_MESH, ix, iy), terrain.height_at, embed_fraction=embed_fraction)
    ids = (np.int64(tile_key_int(ix, iy)) << ROCK_ID_K_BITS) + np.arange(len(d), dtype=np.int64)
    return TileRocks(xy, d, ids, np.arange(len(d)) >= n, shape_error, ell.xyz_m, ell.semi_m, ell.yaw_rad)


def tile_meshes(seed: int, tile: Tile) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (R, V, 3) and faces (F, 3) of the meshes of all the tile's rocks (the same arrays
    every time they are asked for)."""
    return ellipsoid_meshes(tile.rocks.ellipsoids(), tile_rng(seed, STREAM_BUMPS, tile.ix, tile.iy))


def tile_rock_set(tile: Tile, vertices_m: np.ndarray, faces: np.ndarray, keep: np.ndarray) -> Rocks:
    """:class:`sim.rocks.Rocks` (with meshes ``vertices_m`` (R, V, 3) of the whole tile) of the
    tile's rocks selected by ``keep``."""
    r = tile.rocks
    return Rocks.from_vertex_blocks(vertices_m[keep], faces, r.id[keep], xyz_m=r.xyz_m[keep],
                                    size_m=r.diameter_m[keep], height_m=r.height_m[keep])
