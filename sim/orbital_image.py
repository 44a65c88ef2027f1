"""Shaded nadir ("orbital") view of a world, rendered by ray casting terrain and rock meshes."""

from __future__ import annotations

import numpy as np

from sim.world import World

_SOIL_RGB = np.array([0.78, 0.50, 0.32])
_ROCK_RGB = np.array([0.52, 0.44, 0.40])


def orbital_image(
    world: World, gsd_m: float = 0.05, sun_elevation_deg: float = 30.0, sun_azimuth_deg: float = 135.0,
    *, color: bool = True,
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Nadir image of ``world`` at ``gsd_m`` metres per pixel with Lambert shading and cast shadows.

    Returns (uint8 image (H, W, 3) RGB, or (H, W) grey when ``color`` is False; row 0 is the +y
    edge, column 0 the -x edge) and its extent (xmin, xmax, ymin, ymax) in world metres. The sun
    azimuth is counted from +x (east) towards +y (north).
    """
    xmin, xmax, ymin, ymax = world.extent
    W = max(round((xmax - xmin) / gsd_m), 1)
    H = max(round((ymax - ymin) / gsd_m), 1)
    xs = xmin + (np.arange(W) + 0.5) * gsd_m
    ys = ymax - (np.arange(H) + 0.5) * gsd_m
    gx, gy = np.meshgrid(xs, ys)
    top = float(world.terrain.z_m.max() + max(world.rocks.height_m.max(initial=0.0), 0.0) + 10.0)
    n = H * W
    rays = np.zeros((n, 6), dtype=np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2] = gx.ravel(), gy.ravel(), top
    rays[:, 5] = -1.0
    scene = world.raycast_scene()
    t_hit, rock, normal = scene.cast(rays)
    miss = ~np.isfinite(t_hit)
    t_hit[miss] = top - float(world.terrain.z_m.min())
    normal[miss] = (0.0, 0.0, 1.0)
    normal *= np.sign(normal[:, 2:3] + 1e-12)  # upward-facing normals regardless of winding
    el, az = np.deg2rad(sun_elevation_deg), np.deg2rad(sun_azimuth_deg)
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    lambert = np.clip(normal @ sun, 0.0, 1.0)
    hit = rays[:, :3].astype(float)
    hit[:, 2] -= t_hit
    shadow_rays = np.hstack([hit + 0.02 * normal, np.broadcast_to(sun, hit.shape)]).astype(np.float32)
    t_sh, _, _ = scene.cast(shadow_rays)
    lit = ~np.isfinite(t_sh)
    direct = lambert * lit / max(np.sin(el), 0.5)  # flat ground under a 30-degree sun: 1
    shade = 0.3 + 0.7 * direct
    albedo = np.where((rock >= 0)[:, None], _ROCK_RGB, _SOIL_RGB)
    rgb = np.clip(albedo * shade[:, None], 0.0, 1.0)
    img = (255 * rgb).reshape(H, W, 3).astype(np.uint8)
    if not color:
        img = (img.astype(float) @ np.array([0.299, 0.587, 0.114])).astype(np.uint8)
    return img, (xmin, xmax, ymin, ymax)
