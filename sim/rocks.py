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

    @staticmethod
    def from_vertex_blocks(vertices_m: np.ndarray, faces: np.ndarray, ids: np.ndarray, *,
                           xyz_m: np.ndarray | None = None, size_m: np.ndarray | None = None,
                           height_m: np.ndarray | None = None) -> Rocks:
        """Rocks that share one mesh topology: ``vertices_m`` (R, V, 3) world metres, ``faces``
        (F, 3) indices into each rock's V vertices, ``ids`` (R,); vectorised :meth:`from_meshes`.
        ``xyz_m``, ``size_m``, ``height_m``: the rocks' centres, diameters and heights when they are
        known (else the meshes' bounding-box centres, mean caliper widths and heights)."""
        v = np.asarray(vertices_m, dtype=float)
        n = len(v)
        if n == 0:
            return Rocks.from_meshes([])
        if xyz_m is None or height_m is None:
            lo, hi = v.min(axis=1), v.max(axis=1)
        offsets = (np.arange(n, dtype=np.int64) * v.shape[1])[:, None, None]
        return Rocks(
            xyz_m=0.5 * (lo + hi) if xyz_m is None else np.asarray(xyz_m, dtype=float),
            size_m=caliper_diameters(v[:, :, :2]) if size_m is None else np.asarray(size_m, dtype=float),
            id=np.asarray(ids, dtype=np.int64),
            height_m=hi[:, 2] - lo[:, 2] if height_m is None else np.asarray(height_m, dtype=float),
            vertices_m=v.reshape(-1, 3),
            triangles=(np.asarray(faces, dtype=np.int64)[None] + offsets).reshape(-1, 3).astype(np.int32),
            triangle_rock=np.repeat(np.arange(n, dtype=np.int64), len(faces)),
        )

    @staticmethod
    def concat(parts: list[Rocks]) -> Rocks:
        """One :class:`Rocks` holding ``parts`` in order (meshes included)."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return Rocks.from_meshes([])
        v_off = np.cumsum([0] + [len(p.vertices_m) for p in parts[:-1]])
        r_off = np.cumsum([0] + [len(p) for p in parts[:-1]])
        return Rocks(
            xyz_m=np.vstack([p.xyz_m for p in parts]),
            size_m=np.concatenate([p.size_m for p in parts]),
            id=np.concatenate([p.id for p in parts]),
            height_m=np.concatenate([p.height_m for p in parts]),
            vertices_m=np.vstack([p.vertices_m for p in parts]),
            triangles=np.vstack([p.triangles.astype(np.int64) + o for p, o in zip(parts, v_off)]).astype(np.int32),
            triangle_rock=np.concatenate([p.triangle_rock + o for p, o in zip(parts, r_off)]),
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


def caliper_diameters(xy: np.ndarray, n_dir: int = 8) -> np.ndarray:
    """Mean caliper widths (R,) of R point sets ``xy`` (R, P, 2) over ``n_dir`` directions."""
    ang = np.arange(n_dir) * np.pi / n_dir
    proj = xy @ np.stack([np.cos(ang), np.sin(ang)])
    return np.mean(proj.max(axis=1) - proj.min(axis=1), axis=1)


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


@dataclass(frozen=True)
class RockEllipsoids:
    """Rocks as the squashed ellipsoids their meshes perturb: centres ``xyz_m`` (R, 3) (world;
    the rock's true centre), ``semi_m`` (R, 3) semi-axes (x, y horizontal before the yaw, z up),
    ``yaw_rad`` (R,). Diameter (mean caliper width of the horizontal ellipse) and height (2 semi z)
    follow."""

    xyz_m: np.ndarray
    semi_m: np.ndarray
    yaw_rad: np.ndarray

    def __len__(self) -> int:
        return len(self.yaw_rad)

    @property
    def height_m(self) -> np.ndarray:
        return 2.0 * self.semi_m[:, 2]


def _mean_caliper_unit(aspect: np.ndarray) -> np.ndarray:
    """Mean caliper width of ellipses of semi-axes (1, aspect) (R,): mean of 2 sqrt(cos^2 + b^2 sin^2)."""
    ang = np.arange(8) * np.pi / 8
    return np.mean(2.0 * np.sqrt(np.cos(ang)[None] ** 2 + (aspect[:, None] * np.sin(ang)[None]) ** 2), axis=1)


def rock_ellipsoids(xy_m: np.ndarray, diameter_m: np.ndarray, rng: np.random.Generator, ground, *,
                    embed_fraction: float = 0.15) -> RockEllipsoids:
    """Rocks of the shape model of :func:`generate_rocks` (aspect ratios 0.7-1 across, 0.35-0.7
    up, random yaw) whose horizontal ellipse has a mean caliper width of ``diameter_m``, resting on
    the ground ``ground(xy (N, 2)) -> z (N,)`` with ``embed_fraction`` of their height below the
    lowest ground under their outline (sampled at the centre and 8 points of the ellipse)."""
    d = np.asarray(diameter_m, dtype=float)
    xy = np.reshape(np.asarray(xy_m, dtype=float), (-1, 2))
    n = len(d)
    aspect_y, aspect_z = rng.uniform(0.7, 1.0, n), rng.uniform(0.35, 0.7, n)
    yaw = rng.uniform(0.0, 2.0 * np.pi, n)
    a = d / _mean_caliper_unit(aspect_y) if n else np.zeros(0)
    semi = np.column_stack([a, a * aspect_y, 0.5 * d * aspect_z])
    th = np.arange(8) * np.pi / 4
    ex, ey = np.cos(th)[None] * semi[:, :1], np.sin(th)[None] * semi[:, 1:2]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    fx, fy = xy[:, :1] + ex * c - ey * s, xy[:, 1:] + ex * s + ey * c
    if n:
        z_ground = np.reshape(ground(np.column_stack([fx.ravel(), fy.ravel()])), fx.shape).min(axis=1)
        base = np.minimum(z_ground, ground(xy))
    else:
        base = np.zeros(0)
    z_centre = base + semi[:, 2] - embed_fraction * 2.0 * semi[:, 2]
    return RockEllipsoids(np.column_stack([xy, z_centre]), semi, yaw)


def ellipsoid_meshes(rocks: RockEllipsoids, rng: np.random.Generator, subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Meshes of ``rocks``: icospheres scaled to the ellipsoids with a seeded 12 % radial
    roughness per vertex (as :func:`generate_rocks`); vertices (R, V, 3) world, faces (F, 3)."""
    unit_v, unit_f = icosphere(subdivisions)
    n = len(rocks)
    bumps = 1.0 + 0.12 * rng.standard_normal((n, len(unit_v)))
    sm = rocks.semi_m
    bx, by, bz = (bumps * unit_v[:, 0]) * sm[:, :1], (bumps * unit_v[:, 1]) * sm[:, 1:2], (bumps * unit_v[:, 2]) * sm[:, 2:3]
    c, s = np.cos(rocks.yaw_rad)[:, None], np.sin(rocks.yaw_rad)[:, None]
    p = rocks.xyz_m
    v = np.stack([p[:, :1] + bx * c - by * s, p[:, 1:2] + bx * s + by * c, p[:, 2:3] + bz], axis=2)
    return v, unit_f
