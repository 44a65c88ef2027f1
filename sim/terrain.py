"""Terrain heightmaps: a regular grid in the world frame, bilinear heights and normals, a seeded
fractal (sum of smoothed noise octaves) generator scaled to a given relief, and a triangle mesh."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from sim.errors import SimError


@dataclass(frozen=True)
class Heightmap:
    """Heights ``z_m`` (ny, nx) on a regular grid; row i is at y = ymin + i * dy, column j at
    x = xmin + j * dx (world frame, metres); ``extent`` = (xmin, xmax, ymin, ymax)."""

    z_m: np.ndarray
    extent: tuple[float, float, float, float]

    def __post_init__(self) -> None:
        z = np.asarray(self.z_m, dtype=float)
        if z.ndim != 2 or min(z.shape) < 2:
            raise SimError(f"Heightmap.z_m must be a 2D grid of at least 2x2, got shape {z.shape}")
        if not np.all(np.isfinite(z)):
            raise SimError("Heightmap.z_m contains NaN or inf")
        xmin, xmax, ymin, ymax = (float(v) for v in self.extent)
        if not (xmax > xmin and ymax > ymin):
            raise SimError(f"Heightmap.extent must have xmax > xmin and ymax > ymin, got {self.extent}")
        z.setflags(write=False)
        object.__setattr__(self, "z_m", z)
        object.__setattr__(self, "extent", (xmin, xmax, ymin, ymax))

    @property
    def spacing_m(self) -> tuple[float, float]:
        """(dx, dy) grid spacing in metres."""
        ny, nx = self.z_m.shape
        xmin, xmax, ymin, ymax = self.extent
        return (xmax - xmin) / (nx - 1), (ymax - ymin) / (ny - 1)

    def _cell(self, xy: np.ndarray):
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        ny, nx = self.z_m.shape
        dx, dy = self.spacing_m
        fx = np.clip((xy[:, 0] - self.extent[0]) / dx, 0.0, nx - 1.000001)
        fy = np.clip((xy[:, 1] - self.extent[2]) / dy, 0.0, ny - 1.000001)
        j = np.floor(fx).astype(int)
        i = np.floor(fy).astype(int)
        return i, j, fx - j, fy - i

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear terrain height (N,) at world points ``xy`` (N, 2); clamped at the edges."""
        i, j, u, v = self._cell(xy)
        z = self.z_m
        return (
            z[i, j] * (1 - u) * (1 - v) + z[i, j + 1] * u * (1 - v)
            + z[i + 1, j] * (1 - u) * v + z[i + 1, j + 1] * u * v
        )

    def gradient_at(self, xy: np.ndarray) -> np.ndarray:
        """Terrain slope (dz/dx, dz/dy) (N, 2) of the bilinear surface at ``xy`` (N, 2)."""
        i, j, u, v = self._cell(xy)
        z = self.z_m
        dx, dy = self.spacing_m
        gx = ((z[i, j + 1] - z[i, j]) * (1 - v) + (z[i + 1, j + 1] - z[i + 1, j]) * v) / dx
        gy = ((z[i + 1, j] - z[i, j]) * (1 - u) + (z[i + 1, j + 1] - z[i, j + 1]) * u) / dy
        return np.stack([gx, gy], axis=1)

    def normal_at(self, xy: np.ndarray) -> np.ndarray:
        """Unit upward terrain normal (N, 3) at ``xy`` (N, 2)."""
        g = self.gradient_at(xy)
        n = np.column_stack([-g[:, 0], -g[:, 1], np.ones(len(g))])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def contains(self, xy: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        """Boolean (N,): points at least ``margin_m`` inside the extent."""
        xy = np.atleast_2d(xy)
        xmin, xmax, ymin, ymax = self.extent
        return (
            (xy[:, 0] >= xmin + margin_m) & (xy[:, 0] <= xmax - margin_m)
            & (xy[:, 1] >= ymin + margin_m) & (xy[:, 1] <= ymax - margin_m)
        )

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Triangle mesh of the grid: vertices (ny*nx, 3) float, triangles (2*(ny-1)*(nx-1), 3) int32."""
        ny, nx = self.z_m.shape
        xmin, xmax, ymin, ymax = self.extent
        gx, gy = np.meshgrid(np.linspace(xmin, xmax, nx), np.linspace(ymin, ymax, ny))
        verts = np.column_stack([gx.ravel(), gy.ravel(), self.z_m.ravel()])
        idx = np.arange(ny * nx).reshape(ny, nx)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        tris = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])]).astype(np.int32)
        return verts, tris


def fractal_heightmap(
    extent: tuple[float, float, float, float],
    relief_m: float,
    resolution_m: float,
    rng: np.random.Generator,
    *,
    largest_scale_m: float = 25.0,
    octaves: int = 5,
    persistence: float = 0.45,
) -> Heightmap:
    """Seeded fBm-like terrain: octaves of Gaussian-smoothed white noise, each half the length scale
    and ``persistence`` times the amplitude of the previous; rescaled so max - min = ``relief_m``."""
    xmin, xmax, ymin, ymax = extent
    nx = round((xmax - xmin) / resolution_m) + 1
    ny = round((ymax - ymin) / resolution_m) + 1
    z = np.zeros((ny, nx))
    amp, scale = 1.0, largest_scale_m
    for _ in range(octaves):
        sigma_px = max(scale / resolution_m / 2.0, 0.7)
        layer = gaussian_filter(rng.standard_normal((ny, nx)), sigma_px, mode="reflect")
        layer /= layer.std() + 1e-12
        z += amp * layer
        amp *= persistence
        scale /= 2.0
    z -= z.min()
    z *= relief_m / max(z.max(), 1e-12)
    return Heightmap(z, (xmin, xmax, ymin, ymax))
