"""Orthographic nadir ("orbital") view: row 0 at the +y edge of the extent, column 0 at its -x
edge, pixel centres at half-integer offsets. Every sun-facing hit gets its own shadow ray (cast
shadows are the cue nadir rock counting relies on)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.render.config import Lighting, RenderError
from sim.render.shading import Shader, cos_to_sun, shaded_grey, to_uint8
from sim.render.shadows import SunTest
from sim.world import RaycastScene


@dataclass(frozen=True)
class NadirRender:
    """Nadir image: ``image`` (H, W) uint8 grey, ``instance`` (H, W) int32 rock row (-1: soil),
    ``extent`` (xmin, xmax, ymin, ymax) world metres, ``gsd_m`` metres per pixel."""

    image: np.ndarray
    instance: np.ndarray
    extent: tuple[float, float, float, float]
    gsd_m: float

    def pixel_to_world(self, uv: np.ndarray) -> np.ndarray:
        """World xy (N, 2) of continuous pixel coordinates ``uv`` (N, 2) (column, row)."""
        uv = np.reshape(uv, (-1, 2))
        return np.column_stack([self.extent[0] + uv[:, 0] * self.gsd_m, self.extent[3] - uv[:, 1] * self.gsd_m])

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates (N, 2) (column, row) of world points ``xy`` (N, 2)."""
        xy = np.reshape(xy, (-1, 2))
        return np.column_stack([(xy[:, 0] - self.extent[0]) / self.gsd_m, (self.extent[3] - xy[:, 1]) / self.gsd_m])


def render_nadir_view(
    scene: RaycastScene, shader: Shader, gsd_m: float, lighting: Lighting,
    extent: tuple[float, float, float, float], rng: np.random.Generator | None = None, nthreads: int = 0,
) -> NadirRender:
    """Nadir view of ``extent`` (xmin, xmax, ymin, ymax) world metres at ``gsd_m`` m/px; noise
    from ``rng`` (default seeded by the appearance)."""
    if not gsd_m > 0:
        raise RenderError(f"gsd_m must be > 0, got {gsd_m}")
    xmin, xmax, ymin, ymax = extent
    W = round((xmax - xmin) / gsd_m)
    H = round((ymax - ymin) / gsd_m)
    if W < 1 or H < 1:
        raise RenderError(f"extent {extent} is smaller than one {gsd_m} m pixel")
    xs = (xmin + (np.arange(W) + 0.5) * gsd_m).astype(np.float32)
    ys = (ymax - (np.arange(H) + 0.5) * gsd_m).astype(np.float32)
    rays = np.zeros((H, W, 6), dtype=np.float32)
    rays[:, :, 0], rays[:, :, 1] = xs[None, :], ys[:, None]
    rays[:, :, 2], rays[:, :, 5] = scene.z_top_m + 10.0, -1.0
    rays = rays.reshape(-1, 6)
    hits = scene.first_hits(rays, nthreads)
    sun = lighting.sun_dir().astype(np.float32)
    cos_sun = cos_to_sun(hits.normal, sun)
    facing = np.flatnonzero(cos_sun > 0)
    lit = np.zeros(len(rays), dtype=bool)
    lit[facing] = SunTest(scene, rays, hits, sun, nthreads).sunlit(facing)
    # straight down: a hit lies at its ray's own x, y
    grey = shaded_grey(shader, lighting, sun, hits.hit, hits.rock, np.ascontiguousarray(rays[:, 0]),
                       np.ascontiguousarray(rays[:, 1]), cos_sun, lit)
    image = to_uint8(grey.reshape(H, W), shader.app, rng)
    return NadirRender(image, hits.rock.reshape(H, W), (xmin, xmin + W * gsd_m, ymax - H * gsd_m, ymax), gsd_m)
