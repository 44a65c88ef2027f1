"""Rock fields: a power-law size-frequency distribution, perturbed squashed icosphere meshes that
rest on the terrain, and the merged mesh (with a triangle -> rock index) used for ray casting."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import numpy as np

from sim.errors import SimError
from sim.terrain import Heightmap


@dataclass(frozen=True)
class Rocks:
    """True rocks in the world frame.

    ``xyz_m`` (R, 3): centre of each rock's bounding box; ``size_m`` (R,): diameter (mean horizontal
    caliper width); ``id`` (R,) int; ``height_m`` (R,): vertical extent. The merged mesh:
    ``vertices_m`` (V, 3), ``triangles`` (T, 3) int32 and ``triangle_rock`` (T,) the row of the rock
    that owns each triangle.
    """

    xyz_m: np.ndarray
    size_m: np.ndarray
    id: np.ndarray
    height_m: np.ndarray
    vertices_m: np.ndarray = field(repr=False)
    triangles: np.ndarray = field(repr=False)
    triangle_rock: np.ndarray = field(repr=False)

    def __len__(self) -> int:
        return int(self.xyz_m.shape[0])

    @staticmethod
    def from_meshes(meshes: list[tuple[np.ndarray, np.ndarray]], ids: np.ndarray | None = None) -> Rocks:
        """Rocks from per-rock meshes ``[(vertices (V, 3) world m, triangles (T, 3)), ...]``."""
        verts, tris, owner, xyz, size, height = [], [], [], [], [], []
        offset = 0
        for k, (v, t) in enumerate(meshes):
            v = np.asarray(v, dtype=float)
            t = np.asarray(t, dtype=np.int64)
            if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4 or t.ndim != 2 or t.shape[1] != 3:
                raise SimError(f"rock mesh {k}: needs >= 4 vertices (V, 3) and triangles (T, 3)")
            lo, hi = v.min(axis=0), v.max(axis=0)
            xyz.append(0.5 * (lo + hi))
            size.append(caliper_diameter(v[:, :2]))
            height.append(hi[2] - lo[2])
            verts.append(v)
            tris.append(t + offset)
            owner.append(np.full(len(t), k, dtype=np.int64))
            offset += len(v)
        n = len(meshes)
        return Rocks(
            xyz_m=np.reshape(np.array(xyz), (n, 3)),
            size_m=np.array(size, dtype=float),
            id=np.arange(n) if ids is None else np.asarray(ids, dtype=int),
            height_m=np.array(height, dtype=float),
            vertices_m=np.concatenate(verts) if verts else np.zeros((0, 3)),
            triangles=(np.concatenate(tris) if tris else np.zeros((0, 3))).astype(np.int32),
            triangle_rock=np.concatenate(owner) if owner else np.zeros(0, dtype=np.int64),
        )

    def subset(self, keep: np.ndarray) -> Rocks:
        """The rocks selected by boolean/index array ``keep`` (meshes included)."""
        idx = np.arange(len(self))[keep]
        meshes = []
        for k in idx:
            tri_k = self.triangles[self.triangle_rock == k]
            used, inv = np.unique(tri_k, return_inverse=True)
            meshes.append((self.vertices_m[used], inv.reshape(-1, 3)))
        return Rocks.from_meshes(meshes, ids=self.id[idx])


def caliper_diameter(xy: np.ndarray, n_dir: int = 8) -> float:
    """Mean caliper width of a 2D point set (P, 2) over ``n_dir`` directions (metres)."""
    ang = np.arange(n_dir) * np.pi / n_dir
    proj = xy @ np.stack([np.cos(ang), np.sin(ang)])
    return float(np.mean(proj.max(axis=0) - proj.min(axis=0)))


@cache
def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: vertices (V, 3) on the unit sphere, triangles (T, 3) outward-wound."""
    p = (1 + 5**0.5) / 2
    v = [(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p), (0, -1, -p), (0, 1, -p),
         (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
         (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(x, dtype=float) / np.linalg.norm(x) for x in v]
    faces = list(f)
    for _ in range(subdivisions):
        mid: dict[tuple[int, int], int] = {}

        def midpoint(a: int, b: int, mid: dict = mid) -> int:
            key = (min(a, b), max(a, b))
            if key not in mid:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                mid[key] = len(verts) - 1
            return mid[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return np.array(verts), np.array(faces, dtype=np.int32)


def sample_diameters(n: int, d_min: float, d_max: float, alpha: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` diameters (m) from a truncated power law, cumulative N(>D) ~ D^-alpha on [d_min, d_max]."""
    u = rng.random(n)
    r = (d_min / d_max) ** alpha
    return d_min * (1.0 - u * (1.0 - r)) ** (-1.0 / alpha)


def generate_rocks(
    terrain: Heightmap,
    n: int,
    rng: np.random.Generator,
    *,
    d_min: float = 0.1,
    d_max: float = 1.5,
    alpha: float = 2.0,
    embed_fraction: float = 0.15,
    subdivisions: int = 1,
    margin_m: float = 0.5,
) -> Rocks:
    """``n`` rocks at uniform random places, each a randomly perturbed squashed ellipsoid resting on
    ``terrain`` with ``embed_fraction`` of its height buried below the lowest ground under it."""
    unit_v, unit_f = icosphere(subdivisions)
    d = sample_diameters(n, d_min, d_max, alpha, rng)
    xmin, xmax, ymin, ymax = terrain.extent
    xy = np.column_stack([rng.uniform(xmin + margin_m, xmax - margin_m, n),
                          rng.uniform(ymin + margin_m, ymax - margin_m, n)])
    meshes = []
    for k in range(n):
        semi = 0.5 * d[k] * np.array([1.0, rng.uniform(0.7, 1.0), rng.uniform(0.35, 0.7)])
        bumps = 1.0 + 0.12 * rng.standard_normal(len(unit_v))
        v = unit_v * bumps[:, None] * semi
        yaw = rng.uniform(0, 2 * np.pi)
        c, s = np.cos(yaw), np.sin(yaw)
        v = v @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
        foot = v[v[:, 2] < 0.0, :2] + xy[k]
        ground = float(np.min(terrain.height_at(np.vstack([foot, xy[k:k + 1]]))))
        height = v[:, 2].max() - v[:, 2].min()
        v = v + np.array([xy[k, 0], xy[k, 1], ground - v[:, 2].min() - embed_fraction * height])
        meshes.append((v, unit_f))
    return Rocks.from_meshes(meshes)
