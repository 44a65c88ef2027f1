"""Worlds: a terrain heightmap plus rocks, the four reference Mars-yard presets, and the open3d
ray-casting scene (terrain + all rock meshes) that the stereo camera and the orbital view use."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.config import WorldGenConfig
from sim.errors import SimError
from sim.rocks import Rocks, generate_rocks
from sim.terrain import Heightmap, fractal_heightmap


@dataclass(frozen=True)
class WorldPreset:
    """A reference Mars yard: size (m), relief (m), rock count, reference traverse."""

    name: str
    size_x_m: float
    size_y_m: float
    relief_m: float
    n_rocks: int
    traverse_m: float
    duration_s: float

    @property
    def mean_speed_mps(self) -> float:
        return self.traverse_m / self.duration_s


PRESETS: dict[str, WorldPreset] = {
    p.name: p
    for p in (
        WorldPreset("my2020", 43.32, 36.29, 3.01, 2715, 87.05, 905.6),
        WorldPreset("my2021", 47.0, 47.0, 6.58, 740, 90.67, 1374.8),
        WorldPreset("my2022", 50.0, 50.0, 4.82, 294, 85.51, 1046.0),
        WorldPreset("cnes", 57.0, 83.0, 7.81, 468, 70.66, 496.9),
    )
}
# Traverse defaults for imported worlds, which have no reference run.
IMPORTED_TRAVERSE_M = 80.0
IMPORTED_MEAN_SPEED_MPS = 0.08


@dataclass(frozen=True)
class RayHits:
    """First hits of N rays: ``t_m`` (N,) float32 distance along the unit direction (inf: miss),
    ``rock`` (N,) int32 row of the rock hit (-1: terrain or miss), ``normal`` (N, 3) float32 unit
    surface normal turned towards the ray's origin (zero on a miss)."""

    t_m: np.ndarray
    rock: np.ndarray
    normal: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """Boolean (N,): the ray hit a surface."""
        return np.isfinite(self.t_m)


class RaycastScene:
    """open3d ``RaycastingScene`` over the terrain and the merged rock mesh.

    Rays are (N, 6) = (origin xyz, unit direction xyz) in world metres. ``first_hits`` answers in
    float32 (what the renderer needs), ``cast`` in float64, ``unoccluded`` is the cheaper any-hit
    test (shadow rays). ``nthreads`` 0 lets open3d use every core.
    """

    def __init__(self, terrain: Heightmap, rocks: Rocks) -> None:
        from sim.open3d_loader import open3d

        o3d = open3d()
        self._o3c = o3d.core
        self._scene = o3d.t.geometry.RaycastingScene()
        tv, tt = terrain.mesh()
        self.terrain_geometry = self._scene.add_triangles(
            o3d.core.Tensor(tv.astype(np.float32)), o3d.core.Tensor(tt.astype(np.uint32))
        )
        self.rock_geometry = -1
        self._triangle_rock = np.asarray(rocks.triangle_rock, dtype=np.int32)
        if len(rocks):
            self.rock_geometry = self._scene.add_triangles(
                o3d.core.Tensor(rocks.vertices_m.astype(np.float32)),
                o3d.core.Tensor(rocks.triangles.astype(np.uint32)),
            )
        z_top = float(terrain.z_m.max())
        if len(rocks):
            z_top = max(z_top, float(rocks.vertices_m[:, 2].max()))
        self.z_bottom_m = float(terrain.z_m.min())  # lowest terrain point
        self.z_top_m = z_top  # highest vertex of terrain or rocks: nothing blocks a ray above it

    def _tensor(self, rays: np.ndarray):
        rays = np.ascontiguousarray(rays, dtype=np.float32).reshape(-1, 6)
        return rays, self._o3c.Tensor.from_numpy(rays)

    def first_hits(self, rays: np.ndarray, nthreads: int = 0) -> RayHits:
        """First surface hit of each ray (N, 6), float32 (see :class:`RayHits`)."""
        rays, tensor = self._tensor(rays)
        if len(rays) == 0:
            return RayHits(np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32))
        ans = self._scene.cast_rays(tensor, nthreads=nthreads)
        t = ans["t_hit"].numpy()
        rock = np.full(len(rays), -1, dtype=np.int32)
        on_rock = np.flatnonzero(ans["geometry_ids"].numpy() == self.rock_geometry)  # a miss has INVALID_ID
        rock[on_rock] = self._triangle_rock[ans["primitive_ids"].numpy()[on_rock]]
        normal = ans["primitive_normals"].numpy()
        # meshes wound inwards (rare, imported ones) give normals facing away from the ray
        dn = normal[:, 0] * rays[:, 3]
        dn += normal[:, 1] * rays[:, 4]
        dn += normal[:, 2] * rays[:, 5]
        back = np.flatnonzero(dn > -1e-12)
        normal[back] = -normal[back]
        return RayHits(t, rock, normal)

    def cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hits of rays (N, 6), float64: ``t_hit`` (N,) (inf on a miss), ``rock`` (N,) int64
        rock row (-1 for terrain or a miss), ``normal`` (N, 3) unit normal towards the ray's origin."""
        h = self.first_hits(rays)
        return h.t_m.astype(float), h.rock.astype(np.int64), h.normal.astype(float)

    def unoccluded(self, rays: np.ndarray, t_far_m: float = np.inf, nthreads: int = 0) -> np.ndarray:
        """Boolean (N,): rays (N, 6) that meet no surface within ``t_far_m`` (any-hit test)."""
        rays, tensor = self._tensor(rays)
        if len(rays) == 0:
            return np.zeros(0, dtype=bool)
        return ~self._scene.test_occlusions(tensor, tfar=float(t_far_m), nthreads=nthreads).numpy()


@dataclass
class World:
    """A Mars yard: ``terrain`` heightmap, true ``rocks``, and its ``preset`` timing (None if imported)."""

    name: str
    terrain: Heightmap
    rocks: Rocks
    preset: WorldPreset | None = None
    source: str = "procedural"
    _scene: RaycastScene | None = field(default=None, repr=False)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) in world metres."""
        return self.terrain.extent

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Terrain height (N,) under world points ``xy`` (N, 2); rocks not included."""
        return self.terrain.height_at(xy)

    def normal_at(self, xy: np.ndarray) -> np.ndarray:
        """Unit terrain normal (N, 3) under world points ``xy`` (N, 2)."""
        return self.terrain.normal_at(xy)

    def raycast_scene(self) -> RaycastScene:
        """The (cached) ray-casting scene of terrain + rocks."""
        if self._scene is None:
            self._scene = RaycastScene(self.terrain, self.rocks)
        return self._scene


def build_world(name: str, seed: int, cfg: WorldGenConfig | None = None) -> World:
    """The world named ``name``: a preset (procedural, seeded) or a Gazebo model directory."""
    cfg = cfg or WorldGenConfig()
    if name in PRESETS:
        p = PRESETS[name]
        rng = np.random.default_rng([seed, 1])
        extent = (-p.size_x_m / 2, p.size_x_m / 2, -p.size_y_m / 2, p.size_y_m / 2)
        terrain = fractal_heightmap(extent, p.relief_m, cfg.resolution_m, rng)
        rocks = generate_rocks(
            terrain, cfg.n_rocks if cfg.n_rocks is not None else p.n_rocks, rng,
            d_min=cfg.rock_min_diameter_m, d_max=cfg.rock_max_diameter_m,
            alpha=cfg.rock_cumulative_exponent, embed_fraction=cfg.rock_embed_fraction,
            subdivisions=cfg.rock_icosphere_subdivisions,
        )
        return World(name=name, terrain=terrain, rocks=rocks, preset=p)
    from sim.tiled.presets import TILED_PRESETS

    if name in TILED_PRESETS:
        raise SimError(f"{name!r} is a kilometre preset: it is streamed, not built in memory "
                       f"(fgslam sim, or sim.tiled.simulate_to_bag(sim.tiled.preset_config({name!r}), out))")
    path = Path(name)
    if path.is_dir():
        from sim.gazebo_import import import_gazebo_world

        return import_gazebo_world(path)
    raise SimError(f"unknown world {name!r}: use one of {sorted(PRESETS)} or a Gazebo model directory")
